#pragma once
// Right-preconditioned restarted GMRES (Saad & Schultz 1986; Saad, "Iterative Methods for
// Sparse Linear Systems", Alg. 9.5) for operators given as callables: the nonsymmetric
// Newton steps of static solves (the corotational tangent with its rotation part),
// preconditioned by a factor of the symmetric part, take a handful of iterations. Same calling
// convention and result record as pcg().
#include <algorithm>
#include <cmath>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/solver/pcg.hpp"

namespace needle_sim {

// Krylov vectors kept before a restart: bounds the memory (kGmresRestart + 1 vectors of b's
// size) whatever max_iterations is.
constexpr int kGmresRestart = 50;

// Solves A x = b from the x passed in; stops when the true residual ||b - A x|| (recomputed
// at every restart and at the end) is <= tol ||b||, or after max_iterations in all.
template <class Apply, class Precondition>
PcgResult gmres(const Apply& apply, const Precondition& precondition, const VecX& b, VecX& x, double tol,
                int max_iterations) {
  PcgResult res;
  if (solvedByZero(b, x, res)) return res;
  const double bnorm = b.norm();
  if (x.size() != b.size()) x.setZero(b.size());
  VecX w(b.size()), z;
  std::vector<VecX> V;
  for (;;) {
    apply(x, w);
    const VecX r = b - w;
    const double beta = r.norm();
    res.relative_residual = beta / bnorm;
    res.converged = beta <= tol * bnorm;
    if (res.converged || !std::isfinite(beta) || res.iterations >= max_iterations) return res;
    const int m = std::min(kGmresRestart, max_iterations - res.iterations);
    V.clear();
    V.push_back(r / beta);
    Eigen::MatrixXd H = Eigen::MatrixXd::Zero(m + 1, m);
    VecX cs(m), sn(m), g = VecX::Zero(m + 1);
    g[0] = beta;
    int k = 0;
    while (k < m) {
      precondition(V[k], z);
      apply(z, w);
      for (int i = 0; i <= k; ++i) {  // modified Gram-Schmidt
        H(i, k) = V[i].dot(w);
        w.noalias() -= H(i, k) * V[i];
      }
      const double h_next = w.norm();
      for (int i = 0; i < k; ++i) {  // the earlier Givens rotations on the new column
        const double t = cs[i] * H(i, k) + sn[i] * H(i + 1, k);
        H(i + 1, k) = -sn[i] * H(i, k) + cs[i] * H(i + 1, k);
        H(i, k) = t;
      }
      const double d = std::hypot(H(k, k), h_next);
      if (!(d > 0) || !std::isfinite(d)) break;  // NaN, or an operator that maps to nothing
      cs[k] = H(k, k) / d;
      sn[k] = h_next / d;
      H(k, k) = d;
      g[k + 1] = -sn[k] * g[k];
      g[k] = cs[k] * g[k];
      ++k;
      if (std::abs(g[k]) <= tol * bnorm || h_next == 0.0) break;
      V.push_back(w / h_next);
    }
    if (k == 0) return res;  // no progress possible: reported with the true residual above
    res.iterations += k;
    const VecX y = H.topLeftCorner(k, k).triangularView<Eigen::Upper>().solve(g.head(k));
    VecX u = VecX::Zero(b.size());
    for (int i = 0; i < k; ++i) u.noalias() += y[i] * V[i];
    precondition(u, z);
    x += z;
  }
}

}  // namespace needle_sim
