#pragma once
// The ROS face of needle_sim: one class built from (nh, private_nh), shared by the node
// (needle_sim_node) and the nodelet (needle_sim/SimulatorNodelet). No physics here: it
// loads a scene, turns validated commands into keyframes of the needles' base trajectories,
// steps the core Simulation on a worker thread paced by a ros::Timer (which follows /clock
// under /use_sim_time), builds messages from what the core computes, and hands them to an
// output thread that sends them (so serialisation and sockets never delay a step).
//
// Parameters (private):
//   ~scene (string, required)      scene YAML file
//   ~set (string list)             key.path=value overrides, as `needle_sim run --set`
//   ~tissue_frame ("tissue")       frame of every output
//   ~command_source ("topic")      topic: needle base poses from <needle>/command_pose;
//                                  scene: follow the scene's own motion keyframes (demo);
//                                  tf: the base pose is the transform ~tissue_frame ->
//                                  ~needle_base_frame (default <needle>_base), read every step
//   ~needle_base_frame             the base frame for tf commands (one needle)
//   ~max_speed (0.05 m/s)          faster commands are clamped to it (warning, counted); a
//                                  command is reached over the interval since the previous
//                                  one (header stamps; at least one step)
//   ~command_timeout (0.5 s)       commands older than this (header stamp) are rejected
//   ~command_latency (0.005 s)     a stamped command is reached at its stamp plus this (or at
//                                  the end of the step, if later): steps do not depend on when
//                                  messages arrive, so a replayed bag gives the same run
//   ~workspace_margin (0.2 m)      commands farther than this from the tissue's box are rejected
//   ~as_fast_as_possible (false)   step back to back instead of at the scene's dt
//   ~display_rate (30 Hz)          rate of the heavy outputs (cloud, surface, error markers, path)
//   ~output_period (0.001 s)       the output thread sends what the steps produced this often
//                                  (the latency it adds is at most this); 0: woken by every
//                                  step (lowest latency, costs the stepping thread ~5-10 %)
//   ~blas_threads (1)              BLAS threads under CHOLMOD (as the needle_sim tool)
// Topics: subscribes <needle>/command_pose (geometry_msgs/PoseStamped; the needle axis is
// the pose's x axis) and <needle>/command_trajectory (needle_sim/NeedleTrajectory: a plan
// that replaces the commands after its arrival); publishes status (needle_sim/SimStatus), <needle>/wrench
// (geometry_msgs/WrenchStamped: the force and moment the needle exerts on its holder, what a
// force/torque sensor at the base reads; it opposes the insertion while the tissue resists),
// <needle>/path (nav_msgs/Path: the centre line), tissue/deformation (sensor_msgs/
// PointCloud2 with x y z dx dy dz von_mises eta), tissue/surface (visualization_msgs/Marker
// TRIANGLE_LIST of the deformed boundary, per-vertex colours by displacement) and
// tissue/error_markers (visualization_msgs/MarkerArray: DELETEALL, then one CUBE_LIST per
// refinement level coloured by eta); the heavy ones only while subscribed, at ~display_rate.
// Diagnostics (diagnostic_updater, 1 Hz): commands rejected / clamped, overruns, failure.
// Targets (the scene's `targets`, and those added by set_target): target/state
// (needle_sim/TargetState, one message per target and step: position, displacement since
// step 0 and since planning, velocity, distance to each needle tip), target
// (geometry_msgs/PointStamped, the primary target: the first, or the last set), both only
// while subscribed; tf frames target/<name> and target (the primary) at ~display_rate.
// Needle tips: tf frame <needle>_tip (x axis along the needle, as the command poses) at
// ~display_rate.
// For an immersed organ, tissue/surface is the organ's own deformed surface.
// Services: reset (std_srvs/Trigger): back to the scene's initial state (and its targets);
// set_target (needle_sim/SetTarget): add or move a target at a planning position;
// predict (needle_sim/PredictInsertion): a planned base trajectory simulated from the current
// state on a copy (the live run goes on meanwhile), on a callback thread of its own.
//   ~predict_dt (0.01 s)              default time step of a prediction
//   ~predict_sample_period (0.05 s)   default spacing of its samples
//   ~predict_max_steps (100000)       longer predictions are refused
#include <ros/ros.h>
#include <boost/make_shared.hpp>

#include <atomic>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <geometry_msgs/PoseStamped.h>
#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SetTarget.h>
#include <ros/callback_queue.h>
#include <std_srvs/Trigger.h>
#include <diagnostic_updater/diagnostic_updater.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_broadcaster.h>
#include <tf2_ros/transform_listener.h>

#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

// Command validation, kept free of ROS so that it can be tested on its own.
struct CommandCheck {
  enum class Verdict { Accept, Clamp, Reject } verdict = Verdict::Accept;
  std::string reason;
  BasePose pose;
};
// A base pose command (position, orientation as a quaternion whose x axis is the needle
// axis) checked against the last commanded pose `last`, the time dt since it, the speed limit, and
// the workspace box [lo - margin, hi + margin]. rest is the scene's base pose: the command
// q = FromTwoVectors(x, rest axis) * AngleAxis(rest roll, x) is the rest orientation, and
// roll is measured about the commanded axis from the smallest rotation that carries the
// rest axis onto it (BaseTrajectory's convention).
CommandCheck checkCommand(const Vec3& position, const Eigen::Quaterniond& orientation, const BasePose& last,
                          const BasePose& rest, double dt, double max_speed, const Vec3& lo, const Vec3& hi,
                          double margin);

// Orientation of a needle's beam node in the command poses' convention (x axis along the
// needle; at rest, the orientation of the scene's base pose): the <needle>_tip frame and the
// path's poses.
Eigen::Quaterniond nodeFrame(const NeedleBody& needle, int node);

class SimulatorRos {
 public:
  // Throws InputError (scene file, key, problem) when the scene cannot be loaded.
  SimulatorRos(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~SimulatorRos();

 private:
  struct Command {
    int needle;
    BasePose pose;
    double interval;  // since the needle's previous command [s]: the base gets this long to get there
    double at;        // simulation time its stamp asks for (stamp + ~command_latency), NaN without a stamp
  };
  struct Plan {  // a validated NeedleTrajectory
    int needle;
    std::vector<std::pair<double, BasePose>> waypoints;  // (time from start, pose)
  };
  void onTrajectory(int needle, const needle_sim::NeedleTrajectory::ConstPtr& msg);
  // Checks a planned trajectory from the base pose `from`; fills plan.waypoints, or returns
  // why it is refused.
  std::string checkPlan(int needle, const needle_sim::NeedleTrajectory& msg, const BasePose& from, Plan& plan) const;
  bool onPredict(needle_sim::PredictInsertion::Request& req, needle_sim::PredictInsertion::Response& res);
  void load();
  void onTimer(const ros::TimerEvent&);
  void onCommand(int needle, const geometry_msgs::PoseStamped::ConstPtr& msg);
  // Validates a base pose command and queues it for the worker (every command source).
  void acceptCommand(int needle, const Vec3& p, const Eigen::Quaterniond& q, const ros::Time& stamp,
                     const std::string& source);
  void lookupTfCommands();  // ~command_source: tf
  bool onReset(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool onSetTarget(needle_sim::SetTarget::Request& req, needle_sim::SetTarget::Response& res);
  void broadcastFrames(const std_msgs::Header& header);  // tf of targets and needle tips, at ~display_rate
  void worker();
  // Messages are built on the worker thread (from the simulation's state, under its lock)
  // and sent by the output thread: serialisation and socket writes, the tf broadcasts, never
  // delay a step. In order; if the sender falls kOutQueue jobs behind, the oldest are dropped
  // (counted in diagnostics).
  template <class M>
  void post(ros::Publisher& pub, M msg) {
    auto m = boost::make_shared<M>(std::move(msg));
    postJob([&pub, m] { pub.publish(m); });
  }
  void postJob(std::function<void()> job);
  void outputLoop();
  void stepOnce();  // with sim_mutex_ held
  // Per step the worker copies the numbers the messages need into a StepFrame (no strings,
  // no message types) and hands it over in one job; the output thread builds and sends
  // status, wrenches and target messages from it, names coming from the frame's Labels.
  struct Labels {  // rebuilt when the scene or the targets change
    std::string scene;
    std::vector<std::string> needles, probes, targets;
    std::vector<Vec3> probe_rest, target_rest, target_start;
    int electrode = -1;  // the needle named "electrode"
  };
  struct StepFrame {
    ros::Time stamp;
    std::shared_ptr<const Labels> labels;
    std::string failure;  // empty while running
    uint64_t step = 0, overruns = 0, rejected = 0, clamped = 0;
    double sim_time = 0, step_ms = 0, step_ms_max = 0, publish_ms = 0, rtf = 0, eta_relative = 0;
    int dofs = 0, elements = 0, linear_iterations = 0, constraint_points = 0;
    bool interaction = false;
    std::vector<InsertionState> states;
    std::vector<Vec3> probe_u, force, moment, tip, target_x, target_v;  // per probe / needle / target
    int primary = 0;
    bool target_point = false, target_state = false;  // subscribed
  };
  void makeLabels();  // with sim_mutex_ held
  void publish(const StepStats& s, double ms);
  void sendStep(const StepFrame& f);  // on the output thread
  void publishDisplay();  // path; snapshot for cloud, surface, error markers (with sim_mutex_ held)
  struct DisplayFrame {
    std_msgs::Header header;
    bool cloud = false, surface = false, errors = false;
    std::shared_ptr<const HexMesh> mesh;
    VecX x, reference;  // reference: the estimate's (empty: none)
    std::vector<int> level;
    std::shared_ptr<const TriangleMesh> organ_rest;  // immersed organ, and its vertices now
    std::vector<Vec3> organ_pos;
  };
  void buildDisplay(const DisplayFrame& f);  // on the output thread
  void diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat);

  ros::NodeHandle nh_, pnh_;
  std::string scene_file_, frame_, command_source_;
  std::vector<std::string> overrides_;
  double max_speed_ = 0.05, command_timeout_ = 0.5, workspace_margin_ = 0.2, display_rate_ = 30;
  double command_latency_ = 0.005;
  double output_period_ = 0.001;
  ros::WallTime last_display_;
  // Display snapshots: the mesh copied once per change (worker thread) ...
  std::shared_ptr<const HexMesh> disp_mesh_;
  const HexMesh* disp_src_ = nullptr;
  int disp_src_elements_ = -1, disp_src_nodes_ = -1;
  // ... and, on the output thread, its model, estimator and boundary faces.
  std::shared_ptr<const HexMesh> out_mesh_;
  std::unique_ptr<CorotationalHexModel> out_model_;
  std::unique_ptr<SprEstimator> out_estimator_;
  std::vector<BoundaryFace> faces_;
  uint64_t diag_rejected_ = 0, diag_clamped_ = 0, diag_overruns_ = 0;
  bool as_fast_ = false;
  Scene scene_;
  Vec3 lo_ = Vec3::Zero(), hi_ = Vec3::Zero();

  std::mutex sim_mutex_;  // guards sim_, last_pose_, counters below
  std::unique_ptr<Simulation> sim_;
  std::vector<BasePose> last_pose_;  // last accepted command per needle (queue_mutex_)
  std::vector<ros::Time> last_stamp_;
  std::string failure_;
  double step_ms_max_ = 0;
  double publish_ms_ = 0;  // last publish() call
  std::deque<std::pair<ros::WallTime, double>> rtf_window_;  // (wall, sim time)

  std::mutex queue_mutex_;  // guards commands_, pending_
  std::condition_variable wake_;
  std::vector<Command> commands_;
  std::vector<Plan> plans_;
  int pending_ = 0;
  ros::Time start_time_, last_tick_;  // ROS time of step 0, of the last tick
  long scheduled_ = 0;                // steps due since start_time_
  bool stop_ = false;
  std::atomic<uint64_t> overruns_{0}, rejected_{0}, clamped_{0};

  std::unique_ptr<tf2_ros::Buffer> tf_buffer_;
  std::unique_ptr<tf2_ros::TransformListener> tf_listener_;
  std::vector<std::string> base_frames_;
  std::atomic<uint64_t> tf_failures_{0};
  ros::Timer timer_;
  std::vector<ros::Subscriber> command_subs_;
  ros::Publisher status_pub_, cloud_pub_, surface_pub_, error_pub_, target_pub_, target_state_pub_;
  std::unique_ptr<tf2_ros::TransformBroadcaster> tf_broadcaster_;
  int primary_target_ = 0;  // sim_mutex_
  std::shared_ptr<const Labels> labels_;  // sim_mutex_
  ros::Timer diag_timer_;
  std::unique_ptr<diagnostic_updater::Updater> updater_;
  std::vector<ros::Publisher> wrench_pubs_, path_pubs_;
  ros::ServiceServer reset_srv_, set_target_srv_, predict_srv_;
  std::mutex out_mutex_;
  std::condition_variable out_cv_;
  std::deque<std::function<void()>> out_queue_;
  bool out_stop_ = false;
  bool out_idle_ = false;  // the output thread waits for a job (out_mutex_)
  static constexpr size_t kOutQueue = 20000;
  std::atomic<uint64_t> out_dropped_{0};
  std::atomic<double> out_ms_total_{0.0};
  std::thread out_thread_;
  double predict_dt_ = 0.01, predict_sample_period_ = 0.05;
  int predict_max_steps_ = 100000;
  ros::CallbackQueue predict_queue_;  // predictions take their own thread
  std::unique_ptr<ros::AsyncSpinner> predict_spinner_;
  std::thread thread_;
};

}  // namespace needle_sim
