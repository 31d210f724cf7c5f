#pragma once
// What rviz shows, at ~display_rate and only while someone subscribes: the deformed tissue
// (~tissue/deformation PointCloud2 with x y z dx dy dz von_mises eta; ~tissue/surface, a
// semi-transparent TRIANGLE_LIST coloured by |u| on a scale that changes slowly, with its
// legend in ~tissue/legend), the error indicator per refinement level
// (~tissue/error_markers; these three fields at most at ~field_rate), each needle (~<needle>/path, ~<needle>/marker, and ~<needle>/tip_path,
// the centre line of its cut path where it is now), the targets
// (~target/markers: each target, its error bound's sphere and the online estimate's 95 %
// ellipsoid), and the tf frames <needle>_tip, <needle>_base, <needle>_bevel (bevel
// tips: y along the bevel), target/<name>, target
// (and ~parent_frame -> ~tissue_frame, static). Snapshots are taken on the stepping thread
// (positions only); fields and messages are built on the output thread.
#include <ros/ros.h>
#include <tf2_ros/static_transform_broadcaster.h>
#include <tf2_ros/transform_broadcaster.h>

#include <atomic>
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/tissue_snapshot.hpp"
#include "step_frame.hpp"

namespace needle_sim {

struct NodeParameters;
class OutputQueue;
class Simulation;

class DisplayOutputs {
 public:
  DisplayOutputs(ros::NodeHandle& pnh, const NodeParameters& p, const Scene& scene, OutputQueue& out);
  // On the stepping thread, the simulation's lock held.
  // predictions: the online estimate's per target (NodeAssimilation; empty: none), drawn as
  // its 95 % ellipsoid.
  void publish(const Simulation& sim, const std::shared_ptr<const ObservableNames>& names, int primary_target,
               const Observables& obs, std::vector<TargetPrediction> predictions);
  double rate() const { return rate_; }
  void setRate(double hz) { rate_ = hz; }
  double range() const { return range_; }  // |u| at the top of the colour scale [m]

 private:
  struct Frame;
  void build(const Frame& f);  // on the output thread
  void updateRange(double umax, double t);

  const NodeParameters& p_;
  OutputQueue& out_;
  std::atomic<double> rate_;
  std::atomic<double> range_;
  double peak_ = 0, peak_time_ = 0;
  double last_fields_ = -1e300;  // wall time of the last fields' snapshot (stepping thread)
  bool broadcast_bases_ = true;
  std::vector<double> radius_;
  double target_size_ = 0;  // set from the tissue's size on first use
  ros::Publisher cloud_pub_, surface_pub_, legend_pub_, error_pub_, target_markers_pub_;
  std::vector<ros::Publisher> path_pubs_, tip_path_pubs_, needle_marker_pubs_;
  tf2_ros::TransformBroadcaster tf_;
  std::unique_ptr<tf2_ros::StaticTransformBroadcaster> static_tf_;
  SnapshotTaker snapshots_;
  DisplayFieldBuilder fields_;  // output thread
};

}  // namespace needle_sim
