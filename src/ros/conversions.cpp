#include "conversions.hpp"

#include <limits>

namespace needle_sim {

geometry_msgs::Point toPoint(const Vec3& v) {
  geometry_msgs::Point p;
  p.x = v.x(), p.y = v.y(), p.z = v.z();
  return p;
}

geometry_msgs::Vector3 toVector(const Vec3& v) {
  geometry_msgs::Vector3 p;
  p.x = v.x(), p.y = v.y(), p.z = v.z();
  return p;
}

geometry_msgs::Quaternion toQuaternion(const Eigen::Quaterniond& q) {
  geometry_msgs::Quaternion m;
  m.w = q.w(), m.x = q.x(), m.y = q.y(), m.z = q.z();
  return m;
}

geometry_msgs::Pose toPose(const Vec3& p, const Eigen::Quaterniond& q) {
  geometry_msgs::Pose m;
  m.position = toPoint(p);
  m.orientation = toQuaternion(q);
  return m;
}

Rigid fromTransform(const geometry_msgs::Transform& t) {
  Rigid r;
  r.rotation = fromQuaternion(t.rotation).normalized();
  r.translation = fromVector(t.translation);
  return r;
}

PoseCommand toCommand(const geometry_msgs::Pose& p, const Rigid& to_tissue, double stamp) {
  PoseCommand c;
  c.position = to_tissue.apply(fromPoint(p.position));
  c.orientation = to_tissue.apply(fromQuaternion(p.orientation));
  c.stamp = stamp;
  return c;
}

std::vector<PlanWaypoint> toWaypoints(const needle_sim::NeedleTrajectory& m, const Rigid& to_tissue) {
  std::vector<PlanWaypoint> w;
  for (const auto& p : m.waypoints) {
    PlanWaypoint x;
    x.time = p.time_from_start.toSec();
    x.position = to_tissue.apply(fromPoint(p.pose.position));
    x.orientation = to_tissue.apply(fromQuaternion(p.pose.orientation));
    x.spin_rate = p.spin_rate;
    x.spin_duty = p.spin_duty;
    w.push_back(x);
  }
  return w;
}

bool toWaypoints(const trajectory_msgs::MultiDOFJointTrajectory& m, const std::string& needle, const Rigid& to_tissue,
                 std::vector<PlanWaypoint>& out, std::string& why) {
  out.clear();
  int joint = -1;
  for (size_t j = 0; j < m.joint_names.size(); ++j)
    if (m.joint_names[j] == needle || m.joint_names[j] == needle + "_base") joint = static_cast<int>(j);
  if (joint < 0 && m.joint_names.size() == 1) joint = 0;
  if (joint < 0) {
    why = "no joint named '" + needle + "' or '" + needle + "_base' (and more than one joint)";
    return false;
  }
  for (size_t k = 0; k < m.points.size(); ++k) {
    const auto& p = m.points[k];
    if (p.transforms.size() <= static_cast<size_t>(joint)) {
      why = "point " + std::to_string(k) + " has no transform for joint " + std::to_string(joint);
      return false;
    }
    const auto& t = p.transforms[joint];
    PlanWaypoint x;
    x.time = p.time_from_start.toSec();
    x.position = to_tissue.apply(fromVector(t.translation));
    x.orientation = to_tissue.apply(fromQuaternion(t.rotation));
    out.push_back(x);
  }
  return true;
}

needle_sim::SimStatus statusMessage(const StepFrame& f, const std::string& frame) {
  const ObservableNames& l = *f.names;
  const Observables& o = f.obs;
  needle_sim::SimStatus st;
  st.header.stamp = f.stamp;
  st.header.frame_id = frame;
  st.scene = l.scene;
  st.state = f.state;
  st.message = f.failure;
  st.step = o.step;
  st.sim_time = o.time;
  st.dofs = o.dofs;
  st.tissue_elements = o.tissue_elements;
  st.step_ms = f.step_ms;
  st.step_ms_max = f.step_ms_max;
  st.publish_ms = f.publish_ms;
  st.real_time_factor = f.rtf;
  st.lag = f.lag;
  st.late_steps = f.deadlines.late;
  st.skipped_ticks = f.deadlines.skipped;
  st.late_rate = f.deadlines.late_per_s;
  st.skipped_rate = f.deadlines.skipped_per_s;
  for (int r = 0; r < kGuardRules; ++r) {
    st.guard_rules.push_back(ruleName(static_cast<GuardRule>(r)));
    st.guard_counts.push_back(f.guard[r]);
  }
  st.rejected_commands = f.rejected;
  st.clamped_commands = f.clamped;
  st.linear_iterations = o.stats.linear_iterations;
  st.constraint_points = o.stats.constraint_points;
  st.constraint_residual = f.constraint_residual;
  st.unconverged_steps = f.unconverged;
  st.needles = l.needles;
  st.eta_relative = o.eta_relative;
  st.display_range = f.display_range;
  for (size_t i = 0; i < l.needles.size(); ++i) {
    const bool have = i < o.needles.size();
    st.insertion_states.push_back(have ? toString(o.needles[i].state) : "unknown");
    if (!have) continue;
    st.tips.push_back(toPoint(o.needles[i].tip));
    st.bases.push_back(toPose(o.needles[i].base, o.needles[i].base_frame));
    st.path_curvatures.push_back(o.needles[i].path_curvature);
    st.bevel_directions.push_back(toVector(o.needles[i].bevel_direction));
  }
  for (size_t i = 0; i < o.probe_displacement.size(); ++i) {
    needle_sim::Probe p;
    p.name = l.probes[i];
    p.rest = toPoint(l.probe_rest[i]);
    p.displacement = toVector(o.probe_displacement[i]);
    st.probes.push_back(p);
  }
  return st;
}

std::vector<needle_sim::TargetState> targetStates(const StepFrame& f, const std::string& frame) {
  const ObservableNames& l = *f.names;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<needle_sim::TargetState> out;
  for (size_t i = 0; i < f.obs.targets.size(); ++i) {
    const TargetObservation& t = f.obs.targets[i];
    needle_sim::TargetState m;
    m.header.stamp = f.stamp;
    m.header.frame_id = frame;
    m.name = l.targets[i];
    m.planned = toPoint(l.target_rest[i]);
    m.position = toPoint(t.position);
    m.displacement = toVector(t.displacement);
    m.shift = toVector(t.shift);
    m.velocity = toVector(t.velocity);
    m.needles = l.needles;
    m.tip_distances = t.tip_distances;
    m.needle_tip_distance = t.tip_distances.empty() ? nan : t.tip_distances[0];
    m.displacement_error = toVector(t.has_error ? t.error : Vec3::Constant(nan));
    m.displacement_error_bound = t.has_error ? t.error_bound : nan;
    m.error_step = t.has_error ? t.error_step : -1;
    m.predicted_t = nan;
    m.predicted_position = toPoint(Vec3::Constant(nan));
    m.predicted_covariance.fill(nan);
    if (i < f.predictions.size()) {
      const TargetPrediction& p = f.predictions[i];
      m.predicted_t = p.t;
      m.predicted_position = toPoint(p.position);
      const Mat3 c = p.withBound(t.has_error ? t.error_bound : nan);
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) m.predicted_covariance[3 * r + k] = c(r, k);
    }
    out.push_back(m);
  }
  return out;
}

geometry_msgs::WrenchStamped wrenchMessage(const StepFrame& f, int i, bool in_base, const std::string& tissue_frame) {
  const NeedleObservation& n = f.obs.needles[i];
  geometry_msgs::WrenchStamped w;
  w.header.stamp = f.stamp;
  w.header.frame_id = in_base ? f.names->needles[i] + "_base" : tissue_frame;
  // In the base frame, x is the axial force every report gives (observables.hpp: negative when
  // the tissue resists the insertion).
  w.wrench.force = toVector(in_base ? Vec3(n.axial_force, n.holder_force_base.y(), n.holder_force_base.z()) : n.holder_force);
  w.wrench.torque = toVector(in_base ? n.holder_moment_base : n.holder_moment);
  return w;
}

}  // namespace needle_sim
