#include "display_outputs.hpp"

#include <geometry_msgs/TransformStamped.h>
#include <nav_msgs/Path.h>
#include <sensor_msgs/PointCloud2.h>
#include <sensor_msgs/point_cloud2_iterator.h>
#include <visualization_msgs/MarkerArray.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "conversions.hpp"
#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "node_parameters.hpp"
#include "output_queue.hpp"

namespace needle_sim {

struct DisplayOutputs::Frame {
  std_msgs::Header header;
  double t = 0;  // wall seconds, for the colour scale's memory
  bool cloud = false, surface = false, errors = false;
  TissueSnapshot tissue;
  std::vector<std::string> needles;
  std::vector<std::vector<Vec3>> node_p;  // per needle, per beam node
  std::vector<std::vector<Eigen::Quaterniond>> node_q;
  std::vector<Vec3> bevel;  // per needle, the bevel's lateral direction (zero: a symmetric tip)
  std::vector<bool> path, tip_path, marker;  // subscribed, per needle
  std::vector<std::vector<Vec3>> cut_path;  // per needle, where its cut path is now (when subscribed)
  std::vector<std::string> targets;
  std::vector<Vec3> target_x;
  std::vector<double> target_bound;  // per target, the error bound's radius (< 0: none)
  std::vector<TargetPrediction> predictions;  // per target (empty: none)
  int primary = -1;
  bool target_markers = false;
};

DisplayOutputs::DisplayOutputs(ros::NodeHandle& pnh, const NodeParameters& p, const Scene& scene, OutputQueue& out)
    : p_(p), out_(out), rate_(p.display_rate), range_(p.display_range > 0 ? p.display_range : p.display_range_min) {
  cloud_pub_ = pnh.advertise<sensor_msgs::PointCloud2>("tissue/deformation", 2);
  surface_pub_ = pnh.advertise<visualization_msgs::Marker>("tissue/surface", 2);
  legend_pub_ = pnh.advertise<visualization_msgs::Marker>("tissue/legend", 2, true);
  error_pub_ = pnh.advertise<visualization_msgs::MarkerArray>("tissue/error_markers", 2);
  target_markers_pub_ = pnh.advertise<visualization_msgs::MarkerArray>("target/markers", 2);
  for (const auto& n : scene.needles) {
    path_pubs_.push_back(pnh.advertise<nav_msgs::Path>(n.name + "/path", 10));
    tip_path_pubs_.push_back(pnh.advertise<nav_msgs::Path>(n.name + "/tip_path", 10));
    needle_marker_pubs_.push_back(pnh.advertise<visualization_msgs::Marker>(n.name + "/marker", 10));
    radius_.push_back(n.radius);
  }
  // With tf commands the base frames are the robot's (inputs): not broadcast here.
  broadcast_bases_ = p.command_source != "tf";
  if (!p.parent_frame.empty() && p.publish_tissue_transform) {
    static_tf_ = std::make_unique<tf2_ros::StaticTransformBroadcaster>();
    geometry_msgs::TransformStamped t;
    t.header.stamp = ros::Time::now();
    t.header.frame_id = p.parent_frame;
    t.child_frame_id = p.tissue_frame;
    const auto& q = p.tissue_pose;
    t.transform.translation.x = q[0], t.transform.translation.y = q[1], t.transform.translation.z = q[2];
    t.transform.rotation.x = q[3], t.transform.rotation.y = q[4], t.transform.rotation.z = q[5];
    t.transform.rotation.w = q[6];
    static_tf_->sendTransform(t);
  }
}

void DisplayOutputs::publish(const Simulation& sim, const std::shared_ptr<const ObservableNames>& names, int primary,
                             const Observables& obs, std::vector<TargetPrediction> predictions) {
  auto f = std::make_shared<Frame>();
  f->header.stamp = ros::Time::now();
  f->header.frame_id = p_.tissue_frame;
  f->t = ros::WallTime::now().toSec();
  for (int i = 0; i < sim.numNeedles(); ++i) {
    const NeedleBody& nd = sim.needle(i);
    f->needles.push_back(nd.name());
    std::vector<Eigen::Quaterniond> q;
    for (int k = 0; k < nd.beam().numNodes(); ++k) q.push_back(nodeFrame(nd, k));
    f->node_p.push_back(nd.state().p);
    f->node_q.push_back(std::move(q));
    f->bevel.push_back(i < static_cast<int>(obs.needles.size()) ? obs.needles[i].bevel_direction : Vec3::Zero());
    f->path.push_back(path_pubs_[i].getNumSubscribers() > 0);
    f->marker.push_back(needle_marker_pubs_[i].getNumSubscribers() > 0);
    f->tip_path.push_back(tip_path_pubs_[i].getNumSubscribers() > 0);
    f->cut_path.emplace_back();
    if (f->tip_path.back() && sim.interaction()) sim.interaction()->cutPathNow(i, f->cut_path.back());
  }
  if (sim.hasTissue() && target_size_ <= 0) {  // targets drawn at 1 % of the tissue's size, at least 1 mm
    const HexMesh& m = sim.tissue().mesh();
    target_size_ = std::max(1e-3, 0.01 * (m.boundsMax() - m.boundsMin()).norm());
  }
  f->targets = names->targets;
  for (int i = 0; i < sim.numTargets(); ++i) {
    f->target_x.push_back(sim.targetPosition(i));
    const bool has = i < static_cast<int>(obs.targets.size()) && obs.targets[i].has_error;
    f->target_bound.push_back(has ? obs.targets[i].error_bound : -1.0);
  }
  f->predictions = std::move(predictions);
  f->primary = sim.numTargets() > 0 ? std::min(primary, sim.numTargets() - 1) : -1;
  f->target_markers = target_markers_pub_.getNumSubscribers() > 0;
  if (sim.hasTissue() && f->t - last_fields_ >= 1.0 / p_.field_rate) {
    f->cloud = cloud_pub_.getNumSubscribers() > 0;
    f->surface = surface_pub_.getNumSubscribers() > 0;
    f->errors = error_pub_.getNumSubscribers() > 0;
    if (f->cloud || f->surface || f->errors) {
      f->tissue = snapshots_.take(sim, f->cloud || f->errors, f->surface);
      last_fields_ = f->t;
    }
  }
  out_.post([this, f] { build(*f); });
}

void DisplayOutputs::updateRange(double umax, double t) {
  if (p_.display_range > 0) {
    range_ = p_.display_range;
    return;
  }
  // Rises at once to the largest displacement, falls back with a 5 s time constant: the
  // colours neither flicker from frame to frame nor blow sub-micrometre noise up to red.
  peak_ = std::max(umax, peak_ * std::exp(-(t - peak_time_) / 5.0));
  peak_time_ = t;
  range_ = std::max(p_.display_range_min, peak_);
}

namespace {

std_msgs::ColorRGBA colour(double s, float alpha) {  // 0 -> blue, 0.5 -> green, 1 -> red
  std_msgs::ColorRGBA c;
  s = std::clamp(s, 0.0, 1.0);
  c.r = static_cast<float>(std::clamp(2 * s - 1, 0.0, 1.0));
  c.g = static_cast<float>(1 - std::abs(2 * s - 1));
  c.b = static_cast<float>(std::clamp(1 - 2 * s, 0.0, 1.0));
  c.a = alpha;
  return c;
}

geometry_msgs::TransformStamped transform(const std_msgs::Header& h, const std::string& child, const Vec3& x,
                                          const Eigen::Quaterniond& q) {
  geometry_msgs::TransformStamped t;
  t.header = h;
  t.child_frame_id = child;
  t.transform.translation = toVector(x);
  t.transform.rotation = toQuaternion(q);
  return t;
}

}  // namespace

void DisplayOutputs::build(const Frame& f) {
  const std_msgs::Header& header = f.header;
  // tf: needle tips and bases (command convention), targets.
  std::vector<geometry_msgs::TransformStamped> tfs;
  for (size_t i = 0; i < f.needles.size(); ++i) {
    tfs.push_back(transform(header, f.needles[i] + "_tip", f.node_p[i].back(), f.node_q[i].back()));
    if (f.bevel[i].squaredNorm() > 0) {
      // <needle>_bevel: the tip frame turned about its x axis (the needle's) until its y axis
      // points along the bevel's lateral direction, the side the needle bends to.
      const Eigen::Quaterniond& q = f.node_q[i].back();
      const Vec3 b = q.conjugate() * f.bevel[i];  // in the tip frame
      const Eigen::Quaterniond turn(Eigen::AngleAxisd(std::atan2(b.z(), b.y()), Vec3::UnitX()));
      tfs.push_back(transform(header, f.needles[i] + "_bevel", f.node_p[i].back(), q * turn));
    }
    if (broadcast_bases_) tfs.push_back(transform(header, f.needles[i] + "_base", f.node_p[i].front(), f.node_q[i].front()));
  }
  for (size_t i = 0; i < f.targets.size(); ++i) {
    tfs.push_back(transform(header, "target/" + f.targets[i], f.target_x[i], Eigen::Quaterniond::Identity()));
    if (static_cast<int>(i) == f.primary) tfs.push_back(transform(header, "target", f.target_x[i], Eigen::Quaterniond::Identity()));
  }
  if (!tfs.empty()) tf_.sendTransform(tfs);

  for (size_t i = 0; i < f.needles.size(); ++i) {
    if (f.path[i]) {
      nav_msgs::Path path;
      path.header = header;
      for (size_t k = 0; k < f.node_p[i].size(); ++k) {
        geometry_msgs::PoseStamped ps;
        ps.header = header;
        ps.pose = toPose(f.node_p[i][k], f.node_q[i][k]);
        path.poses.push_back(ps);
      }
      path_pubs_[i].publish(path);
    }
    if (f.tip_path[i]) {
      // The centre line of the cut path where it is now, from the puncture point to the tip's
      // last anchor; each pose's x axis along the path (empty before a puncture).
      nav_msgs::Path path;
      path.header = header;
      const std::vector<Vec3>& c = f.cut_path[i];
      for (size_t k = 0; k < c.size(); ++k) {
        const Vec3 d = c.size() < 2 ? Vec3::UnitX() : k + 1 < c.size() ? Vec3(c[k + 1] - c[k]) : Vec3(c[k] - c[k - 1]);
        geometry_msgs::PoseStamped ps;
        ps.header = header;
        ps.pose = toPose(c[k], Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), d));
        path.poses.push_back(ps);
      }
      tip_path_pubs_[i].publish(path);
    }
    if (f.marker[i]) {  // the needle as a tube of its own diameter
      visualization_msgs::Marker m;
      m.header = header;
      m.ns = f.needles[i];
      m.id = 0;
      m.type = visualization_msgs::Marker::LINE_STRIP;
      m.action = visualization_msgs::Marker::ADD;
      m.pose.orientation.w = 1;
      m.scale.x = 2 * radius_[i];
      m.color.r = m.color.g = m.color.b = 0.85f;
      m.color.a = 1.f;
      for (const Vec3& p : f.node_p[i]) m.points.push_back(toPoint(p));
      needle_marker_pubs_[i].publish(m);
    }
  }
  if (f.target_markers) {
    visualization_msgs::MarkerArray arr;
    for (size_t i = 0; i < f.targets.size(); ++i) {
      visualization_msgs::Marker m;
      m.header = header;
      m.ns = "target/" + f.targets[i];
      m.id = 0;
      m.type = visualization_msgs::Marker::SPHERE;
      m.action = visualization_msgs::Marker::ADD;
      m.pose = toPose(f.target_x[i], Eigen::Quaterniond::Identity());
      m.scale.x = m.scale.y = m.scale.z = target_size_;
      m.color.r = 1.f, m.color.g = 0.2f, m.color.b = 0.8f, m.color.a = 1.f;
      arr.markers.push_back(m);
      // The target's error bound: a translucent sphere of that radius ("target at x +- e").
      visualization_msgs::Marker b = m;
      b.ns = "target_error_bound/" + f.targets[i];
      if (f.target_bound[i] > 0) {
        b.scale.x = b.scale.y = b.scale.z = 2 * f.target_bound[i];
        b.color.r = 1.f, b.color.g = 0.6f, b.color.b = 0.9f, b.color.a = 0.3f;
      } else {
        b.action = visualization_msgs::Marker::DELETE;
      }
      arr.markers.push_back(b);
      // The online estimate's predicted position and its 95 % ellipsoid (chi-square, 3 degrees
      // of freedom: 7.81), the covariance with the discretisation bound's variance added as in
      // TargetState; axes along its eigenvectors.
      visualization_msgs::Marker e = m;
      e.ns = "target_prediction/" + f.targets[i];
      e.action = visualization_msgs::Marker::DELETE;
      if (i < f.predictions.size()) {
        const Mat3 c = f.predictions[i].withBound(f.target_bound[i]);
        const Eigen::SelfAdjointEigenSolver<Mat3> es(0.5 * (c + c.transpose()));
        if (es.info() == Eigen::Success && es.eigenvalues().allFinite() && f.predictions[i].position.allFinite()) {
          Mat3 axes = es.eigenvectors();
          if (axes.determinant() < 0) axes.col(2) *= -1;  // a rotation
          e.action = visualization_msgs::Marker::ADD;
          e.pose = toPose(f.predictions[i].position, Eigen::Quaterniond(axes));
          // At least a nanometre (rviz refuses a zero scale): a flat (rank-deficient)
          // covariance is drawn as a disc.
          const Vec3 r = (7.81 * es.eigenvalues().cwiseMax(0.0)).cwiseSqrt();
          e.scale.x = std::max(2 * r.x(), 1e-9);
          e.scale.y = std::max(2 * r.y(), 1e-9);
          e.scale.z = std::max(2 * r.z(), 1e-9);
          e.color.r = 0.2f, e.color.g = 0.8f, e.color.b = 1.f, e.color.a = 0.4f;
        }
      }
      arr.markers.push_back(e);
    }
    target_markers_pub_.publish(arr);
  }

  if (!f.tissue.mesh) return;
  const DisplayFields d = fields_.build(f.tissue, f.cloud || f.errors, f.surface);
  const HexMesh& mesh = *f.tissue.mesh;
  if (f.cloud) {
    sensor_msgs::PointCloud2 cloud;
    cloud.header = header;
    sensor_msgs::PointCloud2Modifier mod(cloud);
    mod.setPointCloud2Fields(8, "x", 1, sensor_msgs::PointField::FLOAT32, "y", 1, sensor_msgs::PointField::FLOAT32,
                             "z", 1, sensor_msgs::PointField::FLOAT32, "dx", 1, sensor_msgs::PointField::FLOAT32,
                             "dy", 1, sensor_msgs::PointField::FLOAT32, "dz", 1, sensor_msgs::PointField::FLOAT32,
                             "von_mises", 1, sensor_msgs::PointField::FLOAT32, "eta", 1,
                             sensor_msgs::PointField::FLOAT32);
    mod.resize(mesh.numNodes());
    sensor_msgs::PointCloud2Iterator<float> it(cloud, "x");
    for (int n = 0; n < mesh.numNodes(); ++n, ++it) {
      for (int k = 0; k < 3; ++k) {
        it[k] = static_cast<float>(f.tissue.x[3 * n + k]);
        it[3 + k] = static_cast<float>(d.u[3 * n + k]);
      }
      it[6] = d.von_mises[n];
      it[7] = d.eta[n];
    }
    cloud_pub_.publish(cloud);
  }
  if (f.surface) {
    const double umax = d.corner_u.empty() ? 0.0 : *std::max_element(d.corner_u.begin(), d.corner_u.end());
    updateRange(umax, f.t);
    const double range = range_;
    visualization_msgs::Marker m;
    m.header = header;
    m.ns = "tissue_surface";
    m.id = 0;
    m.type = visualization_msgs::Marker::TRIANGLE_LIST;
    m.action = visualization_msgs::Marker::ADD;
    m.pose.orientation.w = 1;
    m.scale.x = m.scale.y = m.scale.z = 1;
    m.color.a = 0.45f;  // see-through: the inserted needle stays visible
    m.points.resize(d.corners.size());
    m.colors.resize(d.corners.size());
    for (size_t i = 0; i < d.corners.size(); ++i) {
      m.points[i] = toPoint(d.corners[i]);
      m.colors[i] = colour(d.corner_u[i] / range, 0.45f);
    }
    surface_pub_.publish(m);
    visualization_msgs::Marker legend;
    legend.header = header;
    legend.ns = "tissue_legend";
    legend.id = 0;
    legend.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
    legend.action = visualization_msgs::Marker::ADD;
    Vec3 top = mesh.boundsMax();
    top.z() += 0.1 * (mesh.boundsMax() - mesh.boundsMin()).norm();
    legend.pose = toPose(top, Eigen::Quaterniond::Identity());
    legend.scale.z = 0.05 * (mesh.boundsMax() - mesh.boundsMin()).norm();
    legend.color.r = legend.color.g = legend.color.b = legend.color.a = 1.f;
    char text[200];
    std::snprintf(text, sizeof text, "|u| blue 0 .. red %.2g mm (now %.2g mm); cubes: error", 1e3 * range, 1e3 * umax);
    legend.text = text;
    legend_pub_.publish(legend);
  }
  if (f.errors) {
    visualization_msgs::MarkerArray arr;
    visualization_msgs::Marker clear;
    clear.header = header;
    clear.action = visualization_msgs::Marker::DELETEALL;
    arr.markers.push_back(clear);
    const int levels = d.level.empty() ? 0 : *std::max_element(d.level.begin(), d.level.end()) + 1;
    for (int L = 0; L < levels; ++L) {
      visualization_msgs::Marker m;
      m.header = header;
      m.ns = "level_" + std::to_string(L);
      m.id = L;
      m.type = visualization_msgs::Marker::CUBE_LIST;
      m.action = visualization_msgs::Marker::ADD;
      m.pose.orientation.w = 1;
      for (int e = 0; e < mesh.numElements(); ++e) {
        if (d.level[e] != L) continue;
        if (m.points.empty()) {  // cube size: the element's rest extent, shrunk so the needle shows through
          m.scale.x = 0.35 * d.extent[e].x(), m.scale.y = 0.35 * d.extent[e].y(), m.scale.z = 0.35 * d.extent[e].z();
        }
        m.points.push_back(toPoint(d.centroid[e]));
        m.colors.push_back(colour(d.eta_max > 0 ? d.element_eta[e] / d.eta_max : 0.0, 0.3f));
      }
      if (!m.points.empty()) arr.markers.push_back(m);
    }
    error_pub_.publish(arr);
  }
}

}  // namespace needle_sim
