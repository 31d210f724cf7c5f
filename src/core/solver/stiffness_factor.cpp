#include "needle_sim/solver/stiffness_factor.hpp"

#include <algorithm>

#include "needle_sim/core/stopwatch.hpp"

namespace needle_sim {

StiffnessFactor::StiffnessFactor(const CorotationalHexModel& model, const DofMap& dofs,
                                 const SymmetricAssembler& assembler, Ordering ordering)
    : model_(model), dofs_(dofs), assembler_(assembler), chol_(ordering) {}

bool StiffnessFactor::factorAt(const VecX& x, const std::vector<Eigen::Quaterniond>& guesses,
                               const ElementBlocks& extra) {
  const auto t0 = steadyNow();
  if (matrix_.nonZeros() == 0) {
    // The pattern only: the stepping thread writes the assembler's values meanwhile.
    const SparseMatrix& a = assembler_.matrix();
    matrix_.resize(a.rows(), a.cols());
    matrix_.resizeNonZeros(a.nonZeros());
    std::copy(a.outerIndexPtr(), a.outerIndexPtr() + a.outerSize() + 1, matrix_.outerIndexPtr());
    std::copy(a.innerIndexPtr(), a.innerIndexPtr() + a.nonZeros(), matrix_.innerIndexPtr());
  }
  double* v = matrix_.valuePtr();
  std::fill(v, v + matrix_.nonZeros(), 0.0);
  hex8::Mat24 Ke;
  const bool guessed = guesses.size() == static_cast<size_t>(model_.numElements());
  for (int e = 0; e < model_.numElements(); ++e) {
    const Mat3 R = guessed ? model_.computeRotation(e, x, guesses[static_cast<size_t>(e)])
                           : model_.computeRotation(e, x, Eigen::Quaterniond::Identity());
    model_.elementStiffness(e, R, Ke);
    assembler_.addElementTo(v, e, Ke.data(), 1.0);
  }
  for (size_t i = 0; i < extra.element.size(); ++i) assembler_.addElementTo(v, extra.element[i], extra.K[i].data(), 1.0);
  if (!chol_.analyzed()) chol_.analyze(matrix_);
  ok_ = chol_.factorize(matrix_);
  factor_ms_ = msSince(t0);
  return ok_;
}

bool StiffnessFactor::solve(const Eigen::MatrixXd& G, Eigen::MatrixXd& Z) const {
  if (!ok_) return false;
  const int nf = dofs_.numFree();
  Eigen::MatrixXd Gf(nf, G.cols()), Zf;
  VecX col, full;
  for (Eigen::Index j = 0; j < G.cols(); ++j) {
    dofs_.gather(G.col(j), col);
    Gf.col(j) = col;
  }
  chol_.solve(Gf, Zf);
  Z.resize(G.rows(), G.cols());
  for (Eigen::Index j = 0; j < G.cols(); ++j) {
    dofs_.scatter(Zf.col(j), full);
    Z.col(j) = full;
  }
  return Z.allFinite();
}

}  // namespace needle_sim
