#include "node_parameters.hpp"

#include <ros/package.h>

#include "needle_sim/scene/scene_path.hpp"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <string>
#include <vector>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

namespace {

// ~set: scene overrides, a list of "key=value" strings. A string is one override (its value
// is YAML of its own, e.g. a map), or a YAML list when it starts with '[': rosrun's
// `_set:="['a=1', 'b=2']"` hands the node a string, and taking it for no override (as
// before) ran the scene without them, silently. Anything else is refused.
void readOverrides(const ros::NodeHandle& pnh, std::vector<std::string>& out) {
  XmlRpc::XmlRpcValue set;
  if (!pnh.getParam("set", set)) return;
  const char* what = "must be a list of 'key=value' strings (or one such string)";
  if (set.getType() == XmlRpc::XmlRpcValue::TypeArray) {
    for (int i = 0; i < set.size(); ++i) {
      if (set[i].getType() != XmlRpc::XmlRpcValue::TypeString)
        throw InputError("", "~set", std::string(what) + "; item " + std::to_string(i) + " is not a string");
      out.push_back(static_cast<std::string>(set[i]));
    }
    return;
  }
  if (set.getType() != XmlRpc::XmlRpcValue::TypeString) throw InputError("", "~set", what);
  const std::string text = static_cast<std::string>(set);
  const size_t first = text.find_first_not_of(" \t");
  if (first == std::string::npos) return;  // blank: none
  if (text[first] != '[') {
    out.push_back(text);
    return;
  }
  YAML::Node y;
  try {
    y = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    throw InputError("", "~set", std::string(what) + "; '" + text + "' is not YAML: " + e.what());
  }
  if (y.IsSequence()) {
    for (const auto& item : y) {
      if (!item.IsScalar()) throw InputError("", "~set", std::string(what) + "; '" + text + "' holds a non-string item");
      out.push_back(item.as<std::string>());
    }
  } else {
    throw InputError("", "~set", std::string(what) + ", got '" + text + "'");
  }
}

}  // namespace

NodeParameters readParameters(const ros::NodeHandle& pnh) {
  NodeParameters p;
  if (!pnh.getParam("scene", p.scene_file))
    throw InputError("", "~scene", "missing private parameter: the scene YAML file");
  // A scene by name (scene:=dbs_adaptive.yaml): the package's, as the tool finds it.
  p.scene_file = resolveScenePath(p.scene_file, ros::package::getPath("needle_sim"));
  readOverrides(pnh, p.overrides);
  pnh.param("deterministic_factor", p.deterministic_factor, p.deterministic_factor);
  pnh.param("rotation_drift", p.rotation_drift, p.rotation_drift);
  if (!(p.rotation_drift <= 0.5))
    throw InputError("", "~rotation_drift", "must be at most 0.5 rad (0: the rotations of every step; < 0: automatic)");
  pnh.param("tissue_frame", p.tissue_frame, p.tissue_frame);
  if (p.tissue_frame.empty()) throw InputError("", "~tissue_frame", "must not be empty");
  pnh.param("parent_frame", p.parent_frame, p.parent_frame);
  std::vector<double> pose;
  if (pnh.getParam("tissue_pose", pose)) {
    if (pose.size() != 7) throw InputError("", "~tissue_pose", "must be [x, y, z, qx, qy, qz, qw]");
    double n = 0;
    for (int i = 0; i < 7; ++i) {
      if (!std::isfinite(pose[i])) throw InputError("", "~tissue_pose", "must be finite");
      p.tissue_pose[i] = pose[i];
      if (i >= 3) n += pose[i] * pose[i];
    }
    if (std::abs(std::sqrt(n) - 1) > 1e-6) throw InputError("", "~tissue_pose", "the quaternion must have norm 1");
  }
  pnh.param("publish_tissue_transform", p.publish_tissue_transform, p.publish_tissue_transform);
  pnh.param("command_source", p.command_source, p.command_source);
  if (p.command_source != "topic" && p.command_source != "scene" && p.command_source != "tf")
    throw InputError("", "~command_source", "must be topic, scene or tf, got '" + p.command_source + "'");
  pnh.param("needle_base_frame", p.needle_base_frame, p.needle_base_frame);
  pnh.param("allow_empty_frame", p.allow_empty_frame, p.allow_empty_frame);
  pnh.param("wrench_frame", p.wrench_frame, p.wrench_frame);
  pnh.param("wrench_rate", p.wrench_rate, p.wrench_rate);
  if (!(p.wrench_rate >= 0) || !std::isfinite(p.wrench_rate))
    throw InputError("", "~wrench_rate", "must be >= 0 and finite [Hz] (0: once per step)");
  if (p.wrench_frame != "base" && p.wrench_frame != "tissue")
    throw InputError("", "~wrench_frame", "must be base or tissue, got '" + p.wrench_frame + "'");

  CommandLimits& l = p.limits;
  pnh.param("max_speed", l.max_speed, l.max_speed);
  pnh.param("max_angular_speed", l.max_angular_speed, l.max_angular_speed);
  pnh.param("max_angular_speed_inserted", l.max_angular_speed_inserted, l.max_angular_speed_inserted);
  pnh.param("max_future", l.max_future, l.max_future);
  pnh.param("command_timeout", l.command_timeout, l.command_timeout);
  pnh.param("quaternion_tolerance", l.quaternion_tolerance, l.quaternion_tolerance);
  pnh.param("workspace_margin", l.workspace_margin, l.workspace_margin);
  pnh.param("command_latency", l.command_latency, l.command_latency);
  pnh.param("owner_timeout", l.owner_timeout, l.owner_timeout);
  l.validate("~");
  LimitCeilings& c = p.ceilings;
  for (const CeiledLimit& k : kCeiledLimits)
    pnh.param(std::string(k.name) + "_ceiling", c.*k.ceiling, c.*k.ceiling);  // start-up only
  c.validate("~");
  c.check(l, "~");
  pnh.param("max_tip_speed", p.max_tip_speed, p.max_tip_speed);
  if (!(p.max_tip_speed >= 0) || !std::isfinite(p.max_tip_speed))
    throw InputError("", "~max_tip_speed", "must be >= 0 and finite (0: 4 times ~max_speed)");

  pnh.param("as_fast_as_possible", p.as_fast_as_possible, p.as_fast_as_possible);
  pnh.param("display_rate", p.display_rate, p.display_rate);
  if (!(p.display_rate > 0) || !std::isfinite(p.display_rate)) throw InputError("", "~display_rate", "must be > 0");
  pnh.param("field_rate", p.field_rate, p.field_rate);
  if (!(p.field_rate > 0) || !std::isfinite(p.field_rate)) throw InputError("", "~field_rate", "must be > 0");
  pnh.param("display_range", p.display_range, p.display_range);
  if (!(p.display_range >= 0) || !std::isfinite(p.display_range))
    throw InputError("", "~display_range", "must be >= 0 (0: adaptive)");
  pnh.param("display_range_min", p.display_range_min, p.display_range_min);
  if (!(p.display_range_min > 0) || !std::isfinite(p.display_range_min))
    throw InputError("", "~display_range_min", "must be > 0");
  pnh.param("output_period", p.output_period, p.output_period);
  if (!(p.output_period >= 0) || !(p.output_period <= 1.0)) throw InputError("", "~output_period", "must be in [0, 1] s");
  pnh.param("blas_threads", p.blas_threads, p.blas_threads);
  if (p.blas_threads < 1) throw InputError("", "~blas_threads", "must be >= 1");
  pnh.param("setup_threads", p.setup_threads, p.setup_threads);
  if (p.setup_threads < 0 || p.setup_threads > 64)
    throw InputError("", "~setup_threads", "must be in [0, 64] (0: every core), got " + std::to_string(p.setup_threads));
  pnh.param("realtime_priority", p.realtime_priority, p.realtime_priority);
  if (p.realtime_priority < -1 || p.realtime_priority > 99)
    throw InputError("", "~realtime_priority",
                     "must be in [-1, 99] (0: the default scheduler; -1: SCHED_FIFO where permitted), got " +
                         std::to_string(p.realtime_priority));
  pnh.param("predict_dt", p.predict_dt, p.predict_dt);
  pnh.param("predict_sample_period", p.predict_sample_period, p.predict_sample_period);
  pnh.param("predict_max_steps", p.predict_max_steps, p.predict_max_steps);
  if (!(p.predict_dt > 0) || !std::isfinite(p.predict_dt)) throw InputError("", "~predict_dt", "must be > 0");
  if (!(p.predict_sample_period > 0) || !std::isfinite(p.predict_sample_period))
    throw InputError("", "~predict_sample_period", "must be > 0");
  if (p.predict_max_steps < 1) throw InputError("", "~predict_max_steps", "must be >= 1");
  pnh.param("predict_preempt", p.predict_preempt, p.predict_preempt);
  pnh.param("preflight_wall", p.preflight_wall, p.preflight_wall);
  if (!(p.preflight_wall >= 0) || !std::isfinite(p.preflight_wall) || p.preflight_wall > 600)
    throw InputError("", "~preflight_wall", "must be in [0, 600] s (0: no pre-flight)");
  pnh.param("predict_max_wall", p.predict_max_wall, p.predict_max_wall);
  if (!(p.predict_max_wall >= 0) || !std::isfinite(p.predict_max_wall))
    throw InputError("", "~predict_max_wall", "must be >= 0 and finite (0: no limit)");
  pnh.param("predict_max_dt", p.predict_max_dt, p.predict_max_dt);
  if (!(p.predict_max_dt >= 0) || !std::isfinite(p.predict_max_dt))
    throw InputError("", "~predict_max_dt", "must be >= 0 and finite (0: 10 times the scene's dt)");
  pnh.param("insert_speed", p.insert_speed, p.insert_speed);
  if (!(p.insert_speed > 0) || !(p.insert_speed <= l.max_speed))
    throw InputError("", "~insert_speed", "must be in (0, ~max_speed]");
  pnh.param("target_error_period", p.target_error_period, p.target_error_period);
  if (!(p.target_error_period >= 0) || !std::isfinite(p.target_error_period))
    throw InputError("", "~target_error_period", "must be >= 0 (0: no error bound)");
  pnh.param("target_error_duty", p.target_error_duty, p.target_error_duty);
  if (!(p.target_error_duty > 0 && p.target_error_duty <= 1))
    throw InputError("", "~target_error_duty", "must be in (0, 1] (the share of the wall time the estimates may take)");
  pnh.param("deadline_warn_fraction", p.deadline_warn_fraction, p.deadline_warn_fraction);
  if (!(p.deadline_warn_fraction >= 0) || !(p.deadline_warn_fraction <= 1))
    throw InputError("", "~deadline_warn_fraction", "must be in [0, 1]");
  // ~assimilation/keys: a list of scene keys or one comma-separated string (as --assimilate).
  AssimilationParameters& a = p.assimilation;
  XmlRpc::XmlRpcValue keys;
  if (pnh.getParam("assimilation/keys", keys)) {
    const char* what = "must be a list of scene keys or one comma-separated string of them";
    std::vector<std::string> items;
    if (keys.getType() == XmlRpc::XmlRpcValue::TypeArray) {
      for (int i = 0; i < keys.size(); ++i) {
        if (keys[i].getType() != XmlRpc::XmlRpcValue::TypeString) throw InputError("", "~assimilation/keys", what);
        items.push_back(static_cast<std::string>(keys[i]));
      }
    } else if (keys.getType() == XmlRpc::XmlRpcValue::TypeString) {
      std::string k;
      for (char c : static_cast<std::string>(keys) + ",") {
        if (c == ',') {
          items.push_back(k);
          k.clear();
        } else if (c != ' ') {
          k += c;
        }
      }
    } else {
      throw InputError("", "~assimilation/keys", what);
    }
    for (const std::string& k : items)
      if (!k.empty()) a.keys.push_back(k);
  }
  pnh.param("assimilation/every", a.every, a.every);
  pnh.param("assimilation/wrench_noise", a.wrench_noise, a.wrench_noise);
  pnh.param("assimilation/tip_noise", a.tip_noise, a.tip_noise);
  pnh.param("assimilation/target_noise", a.target_noise, a.target_noise);
  pnh.param("assimilation/shape_noise", a.shape_noise, a.shape_noise);
  pnh.param("assimilation/shape_spacing", a.shape_spacing, a.shape_spacing);
  pnh.param("assimilation/outlier_gate", a.outlier_gate, a.outlier_gate);
  pnh.param("assimilation/needle", a.needle, a.needle);
  pnh.param("assimilation/target", a.target, a.target);
  pnh.param("assimilation/max_latency", a.max_latency, a.max_latency);
  pnh.param("assimilation/max_future", a.max_future, a.max_future);
  pnh.param("assimilation/adopt", a.adopt, a.adopt);
  pnh.param("assimilation/adopt_ramp", a.adopt_ramp, a.adopt_ramp);
  if (!(a.max_future >= 0)) throw InputError("", "~assimilation/max_future", "must be a time >= 0 [s]");
  return p;
}

}  // namespace needle_sim
