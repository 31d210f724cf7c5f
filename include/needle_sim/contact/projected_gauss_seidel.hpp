#pragma once
// Projected Gauss-Seidel on the Delassus operator W (paper §2.4): find lambda with
//   u = u_free + W lambda,   each constraint's rows satisfying its law (ContactConstraint::
//   target and ::project). The bilateral rows are eliminated exactly (Schur complement, see
//   the .cpp); the rows with a law are updated one at a time, u incrementally, and the
//   constraint's block projected after each row.
#include <vector>

#include "needle_sim/contact/contact_constraint.hpp"
#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct PgsResult {
  int iterations = 0;
  // Largest change of a multiplier in the last sweep, divided by the largest multiplier or by
  // force_scale if that is larger (multipliers near zero are converged in absolute terms).
  double residual = 0;
  bool converged = false;
};

// lambda (3 per constraint) holds the warm start on entry.
PgsResult projectedGaussSeidel(const Eigen::MatrixXd& W, const VecX& u_free,
                               const std::vector<ContactConstraint*>& constraints, double h, double tolerance,
                               int max_iterations, double force_scale, VecX& lambda);

}  // namespace needle_sim
