#include <cmath>

#include "needle_sim/contact/constraint_solve.hpp"

namespace needle_sim {

// Gauss-Seidel on S only, one row at a time, u incrementally, the constraint's block
// projected after each row; the bounds that depend on lateral forces (the Coulomb cone) use
// lambda_L from the previous sweep.
ConstraintSolveResult projectedGaussSeidel(const Eigen::MatrixXd& W, const VecX& u_free,
                                           const std::vector<ContactConstraint*>& c, double h, double tol,
                                           int max_it, double force_scale, VecX& lambda) {
  const ReducedContactProblem rp(W, u_free, c, h);
  const int nf = static_cast<int>(rp.F.size());
  ConstraintSolveResult r;
  VecX lF = rp.gatherF(lambda);
  rp.scatter(lF, lambda);
  VecX uF = rp.qF + rp.S * lF;
  for (int it = 1; it <= std::max(1, max_it); ++it) {
    double max_delta = 0;
    for (int i = 0; i < nf; ++i) {
      const int row = rp.F[i], p = row / 3, k = row % 3;
      if (!(rp.S(i, i) > 0)) continue;  // a row that moves nothing
      Vec3 l = lambda.segment<3>(3 * p);
      l[k] -= (uF[i] - rp.target[row]) / rp.S(i, i);
      c[p]->project(l, k);
      for (int j = 0; j < 3; ++j) {
        const int fj = rp.fpos[3 * p + j];
        if (fj < 0) continue;  // lateral rows follow from the elimination
        const double d = l[j] - lF[fj];
        if (d == 0) continue;
        uF.noalias() += rp.S.col(fj) * d;
        lF[fj] = l[j];
        lambda[3 * p + j] = l[j];
        max_delta = std::max(max_delta, std::abs(d));
      }
    }
    const VecX old = lambda;
    rp.scatter(lF, lambda);  // lateral forces for the next sweep's bounds
    max_delta = std::max(max_delta, (lambda - old).lpNorm<Eigen::Infinity>());
    if (recordIteration(r, it, max_delta, lambda, force_scale, tol)) break;
  }
  projectOntoLaws(c, lambda);
  return r;
}

}  // namespace needle_sim
