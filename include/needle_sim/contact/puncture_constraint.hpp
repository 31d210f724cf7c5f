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
  // The touch's impact (needle_tissue_interaction.cpp): while the point carries no normal
  // force the impulse that brings the surface to the tip's approach speed, m v, is armed; the
  // first loaded steps' forces spend it (rigid contact stops the surface within a step or a
  // few), and what they spend does not count against the puncture strength.
  bool wasLoaded() const { return was_loaded_; }
  void setWasLoaded(bool loaded) { was_loaded_ = loaded; }
  void armImpact(double impulse) { impulse_left_ = impulse; }
  // This step's share of the impact [N] from its normal force and step h, spent from what is left.
  void spendImpact(double h) {
    impact_ = h > 0 ? std::min(std::max(0.0, lambda[0]) * h, impulse_left_) / h : 0.0;
    impulse_left_ -= impact_ * h;
  }
  double impact() const { return impact_; }

 private:
  double friction_;
  bool was_loaded_ = false;
  double impulse_left_ = 0, impact_ = 0;
};

}  // namespace needle_sim
