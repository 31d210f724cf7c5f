#pragma once
// The needle-tissue constraint problem of one step (paper §2.4): find lambda with
//   u = u_free + W lambda,   each constraint's rows satisfying its law (ContactConstraint::
//   target, ::axialBounds and the puncture cone).
// The bilateral rows (lateral rows of tip and shaft points) are eliminated exactly
// (ReducedContactProblem); two solvers work on what is left (doc/method.md, "Constraint
// solve"):
//  - blockActiveSet (default): the axial rows and the puncture blocks' normal rows, a
//    box-constrained QP once the Coulomb bounds are frozen, are solved exactly by a primal
//    active set method; each puncture block's tangential disc is solved exactly; an outer
//    fixed point, Anderson-accelerated, updates the bounds from the lateral forces. It
//    converges in a few outer iterations even in soft tissue, with a second needle pressing
//    on the surface too (test_constraint_solve).
//  - projectedGaussSeidel: the paper's one-row-at-a-time iteration, kept for comparison; it
//    crawls when soft tissue couples many shaft points strongly.
#include <vector>

#include "needle_sim/contact/contact_constraint.hpp"
#include "needle_sim/core/types.hpp"

namespace needle_sim {

enum class ConstraintSolver { BlockActiveSet, GaussSeidel };

struct ConstraintSolveResult {
  int iterations = 0;  // outer iterations (block) or sweeps (Gauss-Seidel)
  // Largest change of a multiplier in the last iteration, divided by the largest multiplier
  // or by force_scale if that is larger (multipliers near zero are converged in absolute terms).
  double residual = 0;
  bool converged = false;
};

// The problem on the rows that carry a law, F, after eliminating the bilateral rows L:
//   lambda_L = z - Z lambda_F,   u_F = qF + S lambda_F,   S = W_FF - W_FL W_LL^-1 W_LF.
struct ReducedContactProblem {
  ReducedContactProblem(const Eigen::MatrixXd& W, const VecX& u_free, const std::vector<ContactConstraint*>& c,
                        double h);
  // lambda (3 per constraint) from lambda_F, with lambda_L following from the elimination.
  void scatter(const VecX& lF, VecX& lambda) const;
  VecX gatherF(const VecX& lambda) const;

  std::vector<int> L, F;  // rows of W
  std::vector<int> P;     // rows whose force the law prescribes (ContactConstraint::prescribed)
  std::vector<double> prescribed;  // their forces
  std::vector<int> fpos;  // row -> index in F, -1 for an eliminated row
  Eigen::MatrixXd S, Z;
  VecX qF, z, target;
};

// Records iteration `it` whose largest multiplier change was max_delta in r (the residual:
// relative to the largest multiplier or force_scale); true when it meets the tolerance.
bool recordIteration(ConstraintSolveResult& r, int it, double max_delta, const VecX& lambda, double force_scale,
                     double tolerance);

// Each constraint's block projected onto its law with the final lateral forces (a friction
// bound may have moved in a solver's last iteration).
void projectOntoLaws(const std::vector<ContactConstraint*>& constraints, VecX& lambda);

// lambda (3 per constraint) holds the warm start on entry.
ConstraintSolveResult blockActiveSet(const Eigen::MatrixXd& W, const VecX& u_free,
                                     const std::vector<ContactConstraint*>& constraints, double h, double tolerance,
                                     int max_iterations, double force_scale, VecX& lambda);
ConstraintSolveResult projectedGaussSeidel(const Eigen::MatrixXd& W, const VecX& u_free,
                                           const std::vector<ContactConstraint*>& constraints, double h,
                                           double tolerance, int max_iterations, double force_scale, VecX& lambda);

}  // namespace needle_sim
