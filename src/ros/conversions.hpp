#pragma once
// Conversions between ROS messages and the core's types, and the per-step messages built
// from a StepFrame. Pure functions: no node, no state.
#include <geometry_msgs/Point.h>
#include <geometry_msgs/Pose.h>
#include <geometry_msgs/Quaternion.h>
#include <geometry_msgs/Transform.h>
#include <geometry_msgs/Vector3.h>
#include <geometry_msgs/WrenchStamped.h>
#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/SimStatus.h>
#include <needle_sim/TargetState.h>
#include <trajectory_msgs/MultiDOFJointTrajectory.h>

#include <string>
#include <vector>

#include "needle_sim/command/command_guard.hpp"
#include "step_frame.hpp"

namespace needle_sim {

geometry_msgs::Point toPoint(const Vec3& v);
geometry_msgs::Vector3 toVector(const Vec3& v);
geometry_msgs::Quaternion toQuaternion(const Eigen::Quaterniond& q);
geometry_msgs::Pose toPose(const Vec3& p, const Eigen::Quaterniond& q);
inline Vec3 fromPoint(const geometry_msgs::Point& p) { return Vec3(p.x, p.y, p.z); }
inline Vec3 fromVector(const geometry_msgs::Vector3& v) { return Vec3(v.x, v.y, v.z); }
// As given: not normalised (the command guard checks the norm).
inline Eigen::Quaterniond fromQuaternion(const geometry_msgs::Quaternion& q) {
  return Eigen::Quaterniond(q.w, q.x, q.y, q.z);
}

// A rigid transform taking coordinates in a message's frame to the tissue frame.
struct Rigid {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Vec3 translation = Vec3::Zero();
  Vec3 apply(const Vec3& p) const { return rotation * p + translation; }
  // Keeps the quaternion's norm, so that a non-unit command is still seen as one.
  Eigen::Quaterniond apply(const Eigen::Quaterniond& q) const { return rotation * q; }
};
Rigid fromTransform(const geometry_msgs::Transform& t);

PoseCommand toCommand(const geometry_msgs::Pose& p, const Rigid& to_tissue, double stamp);
std::vector<PlanWaypoint> toWaypoints(const needle_sim::NeedleTrajectory& m, const Rigid& to_tissue);
// The waypoints of one joint of a MultiDOFJointTrajectory: the joint named `needle` or
// `needle`_base, or the only one. Returns false (why set) when there is no such joint or a
// point lacks its transform.
bool toWaypoints(const trajectory_msgs::MultiDOFJointTrajectory& m, const std::string& needle, const Rigid& to_tissue,
                 std::vector<PlanWaypoint>& out, std::string& why);

needle_sim::SimStatus statusMessage(const StepFrame& f, const std::string& frame);
// One message per target.
std::vector<needle_sim::TargetState> targetStates(const StepFrame& f, const std::string& frame);
// Needle i's wrench on its holder, stamped in <needle>_base (in_base: force.x is the axial
// force, negative when the tissue resists the insertion, observables.hpp) or the tissue frame.
geometry_msgs::WrenchStamped wrenchMessage(const StepFrame& f, int i, bool in_base, const std::string& tissue_frame);

}  // namespace needle_sim
