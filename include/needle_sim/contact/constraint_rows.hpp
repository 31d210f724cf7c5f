#pragma once
// The rows of one constraint solve (paper §2.4, doc/method.md "Constraint solve"). Row k of
// a constraint point measures the relative velocity d_k . (v_needle - v_tissue): it touches
// the 8 tissue nodes of the point's element (trilinear weights, through the hanging-node
// expansion onto free DOFs) and the 2 nodes of its beam element (Hermite weights, on the
// translations and the spins, centre_line.hpp). H is kept only over the DOFs the rows touch,
// one block per body, so that the Delassus operator
//     W = h (H_T C_T H_T^T + sum_n H_N C_N H_N^T),   C = [A^-1] restricted to those DOFs,
// needs only those columns of each body's inverse.
#include <memory>
#include <vector>

#include "needle_sim/contact/contact_constraint.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

class ConstraintRows {
 public:
  // column_of: scratch of the tissue's free-DOF count, all -1 (left so).
  void build(const std::vector<std::unique_ptr<ContactConstraint>>& constraints, const TissueBody& tissue,
             const std::vector<NeedleBody*>& needles, std::vector<int>& column_of);
  int rows() const { return static_cast<int>(HT_.rows()); }
  // The Delassus operator W for a step of length h.
  Eigen::MatrixXd delassus(const TissueBody& tissue, const std::vector<NeedleBody*>& needles, double h) const;
  // Relative velocities of the rows after the bodies' free motion (the prescribed needle
  // bases included).
  VecX freeVelocity(const TissueBody& tissue, const std::vector<NeedleBody*>& needles) const;
  // The bodies' corrections dv += h A^-1 H^T lambda.
  void correct(const VecX& lambda, double h, TissueBody& tissue, const std::vector<NeedleBody*>& needles) const;

 private:
  struct Point {
    int needle, element;
    double xi;
    Mat3 frame;
  };
  std::vector<Point> points_;
  std::vector<int> tcols_;                // free tissue DOFs touched
  std::vector<std::vector<int>> ncols_;   // per needle, free DOFs touched
  Eigen::MatrixXd HT_;
  std::vector<Eigen::MatrixXd> HN_;
};

}  // namespace needle_sim
