#pragma once
// Shaft (paper §2.1, third kind): a tissue material point on the insertion path held on the
// needle centre line. Rows 1-2 (lateral to the needle axis) are bilateral; row 0 (along the
// axis) is Coulomb friction: |lambda_axial| <= mu (|lambda_lateral| + grip), sticking (no
// relative axial velocity) inside it. grip is the normal force of the tissue's radial
// pressure on the needle wall over the point's share of the path, 2 pi r p spacing
// (interaction.grip_pressure; 0: the paper's cone). The needle point is the closest point
// of the centre line, so the axial gap is zero by construction.
#include <algorithm>
#include <cmath>

#include "needle_sim/contact/contact_constraint.hpp"

namespace needle_sim {

class ShaftConstraint : public ContactConstraint {
 public:
  explicit ShaftConstraint(double friction, double grip = 0.0) : friction_(friction), grip_(grip) {}
  std::unique_ptr<ContactConstraint> clone() const override { return std::make_unique<ShaftConstraint>(*this); }
  ConstraintKind kind() const override { return ConstraintKind::Shaft; }
  Vec3 target(double h) const override { return Vec3(0, -gap[1] / h, -gap[2] / h); }
  void axialBounds(const Vec3& l, double& lo, double& hi) const override {
    hi = friction_ * (std::hypot(l[1], l[2]) + grip_);
    lo = -hi;
  }
  void project(Vec3& l, int) const override {
    double lo, hi;
    axialBounds(l, lo, hi);
    l[0] = std::clamp(l[0], lo, hi);
  }
  // The needle this point is on changed (a radius of its own): the grip follows.
  void setGrip(double grip) { grip_ = grip; }
  void setFriction(double friction) { friction_ = friction; }  // adopted during a run
  double grip() const { return grip_; }
  // The friction bound at the last solve's lateral force.
  double bound() const {
    double lo, hi;
    axialBounds(lambda, lo, hi);
    return hi;
  }

 private:
  double friction_, grip_;
};

}  // namespace needle_sim
