#pragma once
// How a needle base pose is written as a rigid-body pose (doc/ros_api.md, "Frames and
// conventions"): the x axis of the pose's orientation is the needle axis, and the roll is
// the twist about that axis measured from the frame that carries the scene's rest axis onto
// it by the smallest rotation (BaseTrajectory's convention). At rest, the orientation is
// FromTwoVectors(x, rest axis) * AngleAxis(rest roll, x).
#include <Eigen/Geometry>

#include "needle_sim/core/types.hpp"
#include "needle_sim/needle/base_trajectory.hpp"

namespace needle_sim {

class NeedleBody;

// Axis and roll of a unit quaternion, the roll unwrapped to lie within pi of roll_near (so
// that a stream of orientations never asks for a turn of 2 pi between two nearly equal
// poses: q and -q, or an angle crossing +-pi, give the same roll).
BasePose basePoseFrom(const Vec3& position, const Eigen::Quaterniond& unit_q, const BasePose& rest, double roll_near);

// The orientation of a base pose in the same convention (the inverse of basePoseFrom).
Eigen::Quaterniond orientationOf(const BasePose& pose, const BasePose& rest);

// Orientation of a needle's beam node in the convention above (x along the needle; at rest
// the scene's base orientation): the <needle>_tip and <needle>_base frames, the path's poses.
Eigen::Quaterniond nodeFrame(const NeedleBody& needle, int node);

// The angle in (-pi, pi] equal to a modulo 2 pi.
double wrapAngle(double a);

}  // namespace needle_sim
