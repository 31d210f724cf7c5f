#pragma once
// Surface puncture (paper §2.1, first kind): unilateral contact of the needle tip on the
// tissue surface with Coulomb friction. Row 0 is the outward surface normal (gap >= 0 when
// the tip is outside), rows 1-2 tangents. The tip punctures when the normal force exceeds
// the puncture strength (decided by the interaction after the solve).
#include <algorithm>

#include "needle_sim/contact/contact_constraint.hpp"

namespace needle_sim {

class PunctureConstraint : public ContactConstraint {
 public:
  explicit PunctureConstraint(double friction) : friction_(friction) {}
  std::unique_ptr<ContactConstraint> clone() const override { return std::make_unique<PunctureConstraint>(*this); }
  ConstraintKind kind() const override { return ConstraintKind::Puncture; }
  // Normal: do not penetrate by the end of the step; tangents: stick.
  Vec3 target(double h) const override { return Vec3(-gap[0] / h, 0, 0); }
  void project(Vec3& l, int) const override {
    l[0] = std::max(0.0, l[0]);  // compressive only (Kuhn-Tucker)
    // Coulomb cone: |lambda_t| <= mu lambda_n
    const double t = std::hypot(l[1], l[2]), bound = friction_ * l[0];
    if (t > bound) {
      const double s = t > 0 ? bound / t : 0;
      l[1] *= s;
      l[2] *= s;
    }
  }
  double normalForce() const { return lambda[0]; }
  double friction() const { return friction_; }
  void setFriction(double friction) { friction_ = friction; }  // adopted during a run

 private:
  double friction_;
};

}  // namespace needle_sim
