#pragma once
// Shaft (paper §2.1, third kind): a tissue material point on the insertion path held on the
// needle centre line. Rows 1-2 (lateral to the needle axis) are bilateral; row 0 (along the
// axis) is Coulomb friction with a true cone: |lambda_axial| <= mu |lambda_lateral|, sticking
// (no relative axial velocity) inside it. The needle point is the closest point of the centre
// line, so the axial gap is zero by construction.
#include <algorithm>
#include <cmath>

#include "needle_sim/contact/contact_constraint.hpp"

namespace needle_sim {

class ShaftConstraint : public ContactConstraint {
 public:
  explicit ShaftConstraint(double friction) : friction_(friction) {}
  std::unique_ptr<ContactConstraint> clone() const override { return std::make_unique<ShaftConstraint>(*this); }
  ConstraintKind kind() const override { return ConstraintKind::Shaft; }
  Vec3 target(double h) const override { return Vec3(0, -gap[1] / h, -gap[2] / h); }
  void project(Vec3& l, int) const override {
    const double b = friction_ * std::hypot(l[1], l[2]);
    l[0] = std::clamp(l[0], -b, b);
  }

 private:
  double friction_;
};

}  // namespace needle_sim
