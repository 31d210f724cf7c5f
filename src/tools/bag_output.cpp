#include "bag_output.hpp"

#include <geometry_msgs/PointStamped.h>
#include <nav_msgs/Path.h>

#include <algorithm>
#include <stdexcept>

#include "../ros/conversions.hpp"
#include "needle_sim/command/pose_convention.hpp"

namespace needle_sim {

BagOutput::BagOutput(const std::string& path, const std::string& ns, const Simulation& sim, double origin,
                     double path_period)
    : ns_(ns.empty() || ns.back() != '/' ? ns : ns.substr(0, ns.size() - 1)),
      names_(std::make_shared<const ObservableNames>(observableNames(sim))),
      origin_(origin),
      path_period_(path_period) {
  try {
    bag_.open(path, rosbag::bagmode::Write);
  } catch (const rosbag::BagException& e) {
    throw std::runtime_error("cannot write the bag " + path + ": " + e.what());
  }
  open_ = true;
}

BagOutput::~BagOutput() {
  try {
    close();
  } catch (...) {
  }
}

void BagOutput::close() {
  if (open_) bag_.close();
  open_ = false;
}

void BagOutput::record(const Simulation& sim, double step_ms) {
  observe(sim, obs_);
  step_ms_max_ = std::max(step_ms_max_, step_ms);
  StepFrame f;
  f.stamp = ros::Time(origin_ + sim.time());
  f.names = names_;
  f.state = "running";
  f.obs = obs_;
  f.step_ms = step_ms;
  f.step_ms_max = step_ms_max_;
  unconverged_ += sim.lastStats().constraint_converged ? 0 : 1;
  f.unconverged = unconverged_;
  f.constraint_residual = sim.lastStats().constraint_residual;
  const std::string tissue_frame = "tissue";
  auto write = [&](const std::string& topic, const auto& m) {
    bag_.write(topic, f.stamp, m);
    ++messages_;
  };
  write(ns_ + "/status", statusMessage(f, tissue_frame));
  for (size_t i = 0; i < f.obs.needles.size(); ++i)
    write(ns_ + "/" + names_->needles[i] + "/wrench", wrenchMessage(f, static_cast<int>(i), true, tissue_frame));
  if (!f.obs.targets.empty()) {
    for (const auto& m : targetStates(f, tissue_frame)) write(ns_ + "/target/state", m);
    geometry_msgs::PointStamped p;
    p.header.stamp = f.stamp;
    p.header.frame_id = tissue_frame;
    p.point = toPoint(f.obs.targets[0].position);
    write(ns_ + "/target", p);
  }
  if (sim.time() + 1e-9 * path_period_ >= next_path_) {
    while (next_path_ <= sim.time() + 1e-9 * path_period_) next_path_ += path_period_;
    for (int i = 0; i < sim.numNeedles(); ++i) {
      const NeedleBody& nd = sim.needle(i);
      nav_msgs::Path path;
      path.header.stamp = f.stamp;
      path.header.frame_id = tissue_frame;
      for (int k = 0; k < nd.beam().numNodes(); ++k) {
        geometry_msgs::PoseStamped ps;
        ps.header = path.header;
        ps.pose = toPose(nd.state().p[k], nodeFrame(nd, k));
        path.poses.push_back(ps);
      }
      write(ns_ + "/" + names_->needles[i] + "/path", path);
    }
  }
}

}  // namespace needle_sim
