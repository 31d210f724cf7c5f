#pragma once
// Tip (paper §2.1, second kind): after puncture the needle tip is tied to a tissue
// material point. Rows 1-2 (lateral) are bilateral; row 0 (axial) sticks until the axial
// force reaches friction * |lateral| + cutting strength, then the tip cuts: the force stays
// on that bound and the interaction moves the anchor to the new tip position. Pulled back,
// the tip meets friction only (the channel is already cut) and is released.
//
// Bevel tip (doc/method.md "Bevel tip"): while the tip cuts, the tissue's lateral reaction
// on it is the bevel's load, lateral_force along the bevel direction, instead of a lateral
// tie: the sharp tip goes where the load and the needle take it, the cut path follows (the
// interaction lays it where the tip is) and the shaft points behind hold the needle on it.
// Whether the tip cuts is the last step's outcome (set by the interaction after the commit),
// so that the rows' kinds are known before the solve; a tip that stops cutting is tied
// laterally again from the next step.
#include <algorithm>
#include <cmath>

#include "needle_sim/contact/contact_constraint.hpp"

namespace needle_sim {

class TipConstraint : public ContactConstraint {
 public:
  TipConstraint(double friction, double cutting_force, double bevel_lateral_force = 0)
      : friction_(friction), cutting_(cutting_force), bevel_force_(bevel_lateral_force) {}
  std::unique_ptr<ContactConstraint> clone() const override { return std::make_unique<TipConstraint>(*this); }
  ConstraintKind kind() const override { return ConstraintKind::Tip; }
  // Axial force on the needle: negative resists advance (friction + cutting), positive
  // resists retraction (friction only).
  void axialBounds(const Vec3& l, double& lo, double& hi) const override {
    hi = friction_ * std::hypot(l[1], l[2]);
    lo = -(hi + cutting_);
  }
  void project(Vec3& l, int) const override {
    double v;
    for (int k = 1; k < 3; ++k)
      if (prescribed(k, v)) l[k] = v;
    double lo, hi;
    axialBounds(l, lo, hi);
    l[0] = std::clamp(l[0], lo, hi);
  }
  bool prescribed(int row, double& value) const override {
    if (row == 0 || !(bevel_force_ > 0) || !was_cutting_) return false;
    value = bevel_force_ * bevel_dir_[row - 1];
    return true;
  }
  bool bevel() const { return bevel_force_ > 0; }
  // Values adopted during a run (NeedleTissueInteraction::setValues): from the next solve.
  void setForces(double friction, double cutting_force, double bevel_lateral_force) {
    friction_ = friction;
    cutting_ = cutting_force;
    bevel_force_ = bevel_lateral_force;
  }
  // The bevel's lateral direction (world, unit, perpendicular to the tip axis) at the current
  // frame: its components on the lateral rows.
  void setBevelDirection(const Vec3& b) { bevel_dir_ = {frame.col(1).dot(b), frame.col(2).dot(b)}; }
  // The tip cut in the last step (its anchor moved): the bevel's lateral load acts in the next.
  void setWasCutting(bool c) { was_cutting_ = c; }
  bool wasCutting() const { return was_cutting_; }
  // True when the axial force sits on its advancing bound: the tip is cutting.
  bool cutting() const {
    return lambda[0] <= -(friction_ * std::hypot(lambda[1], lambda[2]) + cutting_) * (1 - 1e-9);
  }

 private:
  double friction_, cutting_;
  double bevel_force_ = 0;  // [N]; 0: symmetric tip
  Eigen::Vector2d bevel_dir_ = Eigen::Vector2d::Zero();
  bool was_cutting_ = false;
};

}  // namespace needle_sim
