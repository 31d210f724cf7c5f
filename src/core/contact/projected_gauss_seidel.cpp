#include "needle_sim/contact/projected_gauss_seidel.hpp"

#include <Eigen/Cholesky>
#include <cmath>

namespace needle_sim {

// Rows whose multiplier is unbounded (the lateral rows of tip and shaft points: bilateral
// equalities) are eliminated exactly: with L those rows and F the others,
//   lambda_L = W_LL^-1 (t_L - q_L - W_LF lambda_F),
// leaving the Schur complement S = W_FF - W_FL W_LL^-1 W_LF on the rows that carry a law
// (normal contact, friction, cutting). Gauss-Seidel runs on S only; the laws' bounds that
// depend on lateral forces (the Coulomb cone) use lambda_L from the previous sweep. Many
// shaft points per needle element make W_LL near singular (redundant rows); a direct
// factorisation handles that where plain Gauss-Seidel crawls.
PgsResult projectedGaussSeidel(const Eigen::MatrixXd& W, const VecX& u_free,
                               const std::vector<ContactConstraint*>& c, double h, double tol, int max_it,
                               double force_scale, VecX& lambda) {
  const int np = static_cast<int>(c.size());
  const int m = 3 * np;
  PgsResult r;
  VecX target(m);
  for (int p = 0; p < np; ++p) target.segment<3>(3 * p) = c[p]->target(h);
  std::vector<int> L, F;
  for (int p = 0; p < np; ++p)
    for (int k = 0; k < 3; ++k)
      (c[p]->kind() != ConstraintKind::Puncture && k > 0 ? L : F).push_back(3 * p + k);
  const int nl = static_cast<int>(L.size()), nf = static_cast<int>(F.size());
  auto sub = [&](const std::vector<int>& a, const std::vector<int>& b) {
    Eigen::MatrixXd M(a.size(), b.size());
    for (size_t i = 0; i < a.size(); ++i)
      for (size_t j = 0; j < b.size(); ++j) M(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) = W(a[i], b[j]);
    return M;
  };
  auto vec = [&](const VecX& v, const std::vector<int>& a) {
    VecX o(a.size());
    for (size_t i = 0; i < a.size(); ++i) o[static_cast<Eigen::Index>(i)] = v[a[i]];
    return o;
  };
  // Elimination of L.
  Eigen::MatrixXd Z(nl, nf);
  VecX z(nl);
  Eigen::MatrixXd S = sub(F, F);
  VecX qF = vec(u_free, F);
  if (nl > 0) {
    Eigen::LLT<Eigen::MatrixXd> llt(sub(L, L));
    const Eigen::MatrixXd WLF = sub(L, F);
    Z = llt.solve(WLF);
    z = llt.solve(vec(target, L) - vec(u_free, L));
    S.noalias() -= WLF.transpose() * Z;
    qF.noalias() += WLF.transpose() * z;
  }
  VecX lF = vec(lambda, F), lL(nl);
  auto scatter = [&]() {
    if (nl > 0) lL = z - Z * lF;
    for (int i = 0; i < nl; ++i) lambda[L[i]] = lL[i];
    for (int i = 0; i < nf; ++i) lambda[F[i]] = lF[i];
  };
  scatter();
  // Position of each F row in its constraint block.
  std::vector<int> fpos(m, -1);
  for (int i = 0; i < nf; ++i) fpos[F[i]] = i;
  VecX uF = qF + S * lF;
  for (int it = 1; it <= std::max(1, max_it); ++it) {
    double max_delta = 0;
    for (int i = 0; i < nf; ++i) {
      const int row = F[i], p = row / 3, k = row % 3;
      if (!(S(i, i) > 0)) continue;  // a row that moves nothing
      Vec3 l = lambda.segment<3>(3 * p);
      l[k] -= (uF[i] - target[row]) / S(i, i);
      c[p]->project(l, k);
      for (int j = 0; j < 3; ++j) {
        const int fj = fpos[3 * p + j];
        if (fj < 0) continue;  // lateral rows follow from the elimination
        const double d = l[j] - lF[fj];
        if (d == 0) continue;
        uF.noalias() += S.col(fj) * d;
        lF[fj] = l[j];
        lambda[3 * p + j] = l[j];
        max_delta = std::max(max_delta, std::abs(d));
      }
    }
    const VecX lL_old = lL;
    scatter();  // lateral forces for the next sweep's bounds
    if (nl > 0) max_delta = std::max(max_delta, (lL - lL_old).lpNorm<Eigen::Infinity>());
    const double scale = std::max(lambda.lpNorm<Eigen::Infinity>(), force_scale);
    r.iterations = it;
    r.residual = scale > 0 ? max_delta / scale : 0;
    if (r.residual <= tol) {
      r.converged = true;
      break;
    }
  }
  // Final projection with the final lateral forces (a bound may have moved in the last sweep).
  for (int p = 0; p < np; ++p) {
    Vec3 l = lambda.segment<3>(3 * p);
    c[p]->project(l, 0);
    lambda.segment<3>(3 * p) = l;
  }
  return r;
}

}  // namespace needle_sim
