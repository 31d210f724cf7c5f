#pragma once
// A factor of one body's stiffness alone, K = sum_e R_e K0_e R_e^T + extra blocks (the skull's
// support springs) over its free DOFs, with its own CHOLMOD workspace: for the dual problems
// of the goal-oriented estimates (adapt/goal_estimator.hpp; doc/method.md "Error on target
// motion"). The dynamic step's factor (c_m M + c_k K) is a poor preconditioner of K where the
// tissue is soft and nearly incompressible (on dbs_goal CG took 34 iterations a column, 97 ms
// of a pass), and it belongs to the stepping thread; this one is assembled and factorised by
// whichever thread estimates (a background pass), at the rotations of positions it owns.
// It reads the body's model (element references), DOF map and assembler (pattern and scatter
// map), none of which change while the body lives, so another thread may use it meanwhile.
#include <memory>
#include <vector>

#include <Eigen/Geometry>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"
#include "needle_sim/solver/cholmod_solver.hpp"
#include "needle_sim/solver/dof_map.hpp"
#include "needle_sim/solver/symmetric_assembler.hpp"
#include "needle_sim/solver/system_solver.hpp"

namespace needle_sim {

class StiffnessFactor {
 public:
  StiffnessFactor(const CorotationalHexModel& model, const DofMap& dofs, const SymmetricAssembler& assembler,
                  Ordering ordering);
  StiffnessFactor(const StiffnessFactor&) = delete;
  StiffnessFactor& operator=(const StiffnessFactor&) = delete;

  // Assembles and factorises K at the element rotations of positions x (3n; their polar
  // decompositions start from guesses, one per element), plus `extra`. The first call also
  // copies the pattern and analyses it. False when K is not positive definite.
  bool factorAt(const VecX& x, const std::vector<Eigen::Quaterniond>& guesses, const ElementBlocks& extra);
  // Z = K^-1 G for loads G (3n per column, gathered onto the free DOFs as the step's right-hand
  // sides are); Z: displacements (3n per column: zero on prescribed DOFs, hanging DOFs from
  // their masters). False when the last factorAt failed or the solution is not finite.
  bool solve(const Eigen::MatrixXd& G, Eigen::MatrixXd& Z) const;
  double lastFactorMs() const { return factor_ms_; }  // assembly + factorisation

 private:
  const CorotationalHexModel& model_;
  const DofMap& dofs_;
  const SymmetricAssembler& assembler_;
  CholmodSolver chol_;
  SparseMatrix matrix_;  // the assembler's pattern, values of its own
  bool ok_ = false;
  double factor_ms_ = 0;
};

}  // namespace needle_sim
