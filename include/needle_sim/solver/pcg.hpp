#pragma once
// Preconditioned conjugate gradients for SPD operators given as callables.
#include <cmath>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct PcgResult {
  int iterations = 0;
  double relative_residual = 0.0;  // ||b - A x|| / ||b||
  bool converged = false;
};

// b = 0: x = 0 solves it exactly (and a relative residual has no scale). True when handled.
inline bool solvedByZero(const VecX& b, VecX& x, PcgResult& res) {
  if (b.norm() != 0.0) return false;
  x.setZero(b.size());
  res.converged = true;
  return true;
}

// Solves A x = b starting from the x passed in. apply(v, out) computes out = A v;
// precondition(r, z) computes z = M^{-1} r. Stops when ||b - A x|| <= tol ||b||.
template <class Apply, class Precondition>
PcgResult pcg(const Apply& apply, const Precondition& precondition, const VecX& b, VecX& x,
              double tol, int max_iterations) {
  PcgResult res;
  if (solvedByZero(b, x, res)) return res;
  const double bnorm = b.norm();
  VecX r(b.size()), z, p, Ap(b.size());
  if (x.size() != b.size()) x.setZero(b.size());
  apply(x, Ap);
  r = b - Ap;
  double rnorm = r.norm();
  if (rnorm <= tol * bnorm) {
    res.relative_residual = rnorm / bnorm;
    res.converged = true;
    return res;
  }
  precondition(r, z);
  p = z;
  double rz = r.dot(z);
  for (int k = 1; k <= max_iterations; ++k) {
    apply(p, Ap);
    const double pAp = p.dot(Ap);
    if (!(pAp > 0)) break;  // not SPD (or NaN): report non-convergence
    const double alpha = rz / pAp;
    x.noalias() += alpha * p;
    r.noalias() -= alpha * Ap;
    res.iterations = k;
    rnorm = r.norm();
    if (rnorm <= tol * bnorm) {
      res.converged = true;
      break;
    }
    precondition(r, z);
    const double rz_new = r.dot(z);
    p = z + (rz_new / rz) * p;
    rz = rz_new;
  }
  res.relative_residual = rnorm / bnorm;
  return res;
}

}  // namespace needle_sim
