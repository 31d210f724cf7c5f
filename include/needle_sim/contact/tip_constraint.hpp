#pragma once
// Tip (paper §2.1, second kind): after puncture the needle tip is tied to a tissue
// material point. Rows 1-2 (lateral) are bilateral; row 0 (axial) sticks until the axial
// force reaches friction * |lateral| + cutting strength, then the tip cuts: the force stays
// on that bound and the interaction moves the anchor to the new tip position. Pulled back,
// the tip meets friction only (the channel is already cut) and is released.
#include <algorithm>
#include <cmath>

#include "needle_sim/contact/contact_constraint.hpp"

namespace needle_sim {

class TipConstraint : public ContactConstraint {
 public:
  TipConstraint(double friction, double cutting_force) : friction_(friction), cutting_(cutting_force) {}
  std::unique_ptr<ContactConstraint> clone() const override { return std::make_unique<TipConstraint>(*this); }
  ConstraintKind kind() const override { return ConstraintKind::Tip; }
  // Axial force on the needle: negative resists advance (friction + cutting), positive
  // resists retraction (friction only).
  void axialBounds(const Vec3& l, double& lo, double& hi) const override {
    hi = friction_ * std::hypot(l[1], l[2]);
    lo = -(hi + cutting_);
  }
  void project(Vec3& l, int) const override {
    double lo, hi;
    axialBounds(l, lo, hi);
    l[0] = std::clamp(l[0], lo, hi);
  }
  // True when the axial force sits on its advancing bound: the tip is cutting.
  bool cutting() const {
    return lambda[0] <= -(friction_ * std::hypot(lambda[1], lambda[2]) + cutting_) * (1 - 1e-9);
  }

 private:
  double friction_, cutting_;
};

}  // namespace needle_sim
