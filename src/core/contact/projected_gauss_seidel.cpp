#include "needle_sim/contact/projected_gauss_seidel.hpp"

#include <cmath>

namespace needle_sim {

PgsResult projectedGaussSeidel(const Eigen::MatrixXd& W, const VecX& u_free,
                               const std::vector<ContactConstraint*>& c, double h, double tol, int max_it,
                               double force_scale, VecX& lambda) {
  const int np = static_cast<int>(c.size());
  const int m = 3 * np;
  PgsResult r;
  VecX target(m);
  for (int p = 0; p < np; ++p) target.segment<3>(3 * p) = c[p]->target(h);
  // Start from a projected warm start.
  for (int p = 0; p < np; ++p) {
    Vec3 l = lambda.segment<3>(3 * p);
    for (int k = 0; k < 3; ++k) c[p]->project(l, k);
    lambda.segment<3>(3 * p) = l;
  }
  VecX u = u_free + W * lambda;
  for (int it = 1; it <= max_it; ++it) {
    double max_delta = 0;
    for (int p = 0; p < np; ++p)
      for (int k = 0; k < 3; ++k) {
        const int i = 3 * p + k;
        if (!(W(i, i) > 0)) continue;  // a row that moves nothing (all its DOFs prescribed)
        Vec3 l = lambda.segment<3>(3 * p);
        l[k] -= (u[i] - target[i]) / W(i, i);
        c[p]->project(l, k);
        for (int j = 0; j < 3; ++j) {
          const double d = l[j] - lambda[3 * p + j];
          if (d == 0) continue;
          u.noalias() += W.col(3 * p + j) * d;
          lambda[3 * p + j] = l[j];
          max_delta = std::max(max_delta, std::abs(d));
        }
      }
    const double scale = std::max(lambda.lpNorm<Eigen::Infinity>(), force_scale);
    r.iterations = it;
    r.residual = scale > 0 ? max_delta / scale : 0;
    if (r.residual <= tol) {
      r.converged = true;
      break;
    }
  }
  return r;
}

}  // namespace needle_sim
