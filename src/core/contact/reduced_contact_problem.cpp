#include <algorithm>
#include <Eigen/Cholesky>

#include "needle_sim/contact/constraint_solve.hpp"

namespace needle_sim {

// Rows whose multiplier is unbounded (the lateral rows of tip and shaft points: bilateral
// equalities) are eliminated exactly: with L those rows and F the others,
//   lambda_L = W_LL^-1 (t_L - q_L - W_LF lambda_F),
// leaving the Schur complement S = W_FF - W_FL W_LL^-1 W_LF on the rows that carry a law
// (normal contact, friction, cutting). Many shaft points per needle element make W_LL near
// singular (redundant rows); a direct factorisation handles that where an iteration crawls.
// Rows whose force the law prescribes (P: a cutting bevel tip's lateral rows) are known
// before the solve: their forces go to the right-hand side, u_free + W_{.,P} lambda_P, and
// scatter() writes them back.
ReducedContactProblem::ReducedContactProblem(const Eigen::MatrixXd& W, const VecX& u_free,
                                             const std::vector<ContactConstraint*>& c, double h) {
  const int np = static_cast<int>(c.size());
  const int m = 3 * np;
  target.resize(m);
  for (int p = 0; p < np; ++p) target.segment<3>(3 * p) = c[p]->target(h);
  VecX u = u_free;
  for (int p = 0; p < np; ++p)
    for (int k = 0; k < 3; ++k) {
      double v = 0;
      if (c[p]->prescribed(k, v)) {
        P.push_back(3 * p + k);
        prescribed.push_back(v);
        u.noalias() += W.col(3 * p + k) * v;
      } else {
        (c[p]->kind() != ConstraintKind::Puncture && k > 0 ? L : F).push_back(3 * p + k);
      }
    }
  const int nl = static_cast<int>(L.size()), nf = static_cast<int>(F.size());
  fpos.assign(m, -1);
  for (int i = 0; i < nf; ++i) fpos[F[i]] = i;
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
  S = sub(F, F);
  qF = vec(u, F);
  Z.resize(nl, nf);
  z.resize(nl);
  if (nl > 0) {
    Eigen::LLT<Eigen::MatrixXd> llt(sub(L, L));
    const Eigen::MatrixXd WLF = sub(L, F);
    Z = llt.solve(WLF);
    z = llt.solve(vec(target, L) - vec(u, L));
    S.noalias() -= WLF.transpose() * Z;
    qF.noalias() += WLF.transpose() * z;
  }
}

void ReducedContactProblem::scatter(const VecX& lF, VecX& lambda) const {
  if (!L.empty()) {
    const VecX lL = z - Z * lF;
    for (size_t i = 0; i < L.size(); ++i) lambda[L[i]] = lL[static_cast<Eigen::Index>(i)];
  }
  for (size_t i = 0; i < F.size(); ++i) lambda[F[i]] = lF[static_cast<Eigen::Index>(i)];
  for (size_t i = 0; i < P.size(); ++i) lambda[P[i]] = prescribed[i];
}

VecX ReducedContactProblem::gatherF(const VecX& lambda) const {
  VecX o(F.size());
  for (size_t i = 0; i < F.size(); ++i) o[static_cast<Eigen::Index>(i)] = lambda[F[i]];
  return o;
}

bool recordIteration(ConstraintSolveResult& r, int it, double max_delta, const VecX& lambda, double force_scale,
                     double tolerance) {
  const double scale = std::max(lambda.lpNorm<Eigen::Infinity>(), force_scale);
  r.iterations = it;
  r.residual = scale > 0 ? max_delta / scale : 0;
  r.converged = r.residual <= tolerance;
  return r.converged;
}

void projectOntoLaws(const std::vector<ContactConstraint*>& c, VecX& lambda) {
  for (size_t p = 0; p < c.size(); ++p) {
    Vec3 l = lambda.segment<3>(3 * static_cast<Eigen::Index>(p));
    c[p]->project(l, 0);
    lambda.segment<3>(3 * static_cast<Eigen::Index>(p)) = l;
  }
}

}  // namespace needle_sim
