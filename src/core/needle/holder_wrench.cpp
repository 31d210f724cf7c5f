#include "needle_sim/needle/holder_wrench.hpp"

namespace needle_sim {

void HolderWrenchExtrapolation::afterStep(const Vec3& base, const Vec3& force, const Vec3& moment,
                                          int constraint_points) {
  motion_ = base - base_;
  // A base that moved less than a nanometre gives no slope: the wrench's change over such a
  // step is not the motion's (it would be divided by almost nothing).
  slope_ = stepped_ && constraint_points == points_ && motion_.squaredNorm() > 1e-18;
  if (slope_) {
    dforce_ = force - force_;
    dmoment_ = moment - moment_;
  }
  stepped_ = true;
  points_ = constraint_points;
  base_ = base;
  force_ = force;
  moment_ = moment;
}

void HolderWrenchExtrapolation::at(const Vec3& base, Vec3& force, Vec3& moment) const {
  force = force_;
  moment = moment_;
  if (!slope_) return;
  const double s = (base - base_).dot(motion_) / motion_.squaredNorm();  // steps' worth of the last motion
  force += s * dforce_;
  moment += s * dmoment_;
}

}  // namespace needle_sim
