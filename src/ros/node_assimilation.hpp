#pragma once
// SimulatorRos's online estimation (doc/ros_api.md, "Assimilation"; issue #41): measured
// holder wrenches, tip positions and target positions in, each through stamp and frame checks
// (refused ones are counted, never used); the core's ForceAssimilation
// (calibration/force_assimilation.hpp, what `needle_sim run --assimilate` runs) refitted on a
// thread of its own under SCHED_IDLE, so that it never makes a step late; ~estimate and
// a diagnostics entry out. The live simulation adopts each consistent estimate of the keys it
// can take during a run (Simulation::adoptable: the tissue's Young's modulus, the interaction's
// forces, friction and grip),
// ramped over ~assimilation/adopt_ramp (calibration/parameter_adoption.hpp) so that its
// published force has no jump; the other keys are estimated only.
//
// The refits run the session again from its start: with the scene's own motion, the scene;
// with commands (topic, tf, plans, ~insert), the base poses the needle took at every step,
// replayed through a command pipeline with the node's limits (sim/command_replay.hpp).
#include <ros/ros.h>

#include <diagnostic_updater/diagnostic_updater.h>
#include <geometry_msgs/PointStamped.h>
#include <geometry_msgs/PoseArray.h>
#include <geometry_msgs/WrenchStamped.h>
#include <tf2_ros/buffer.h>

#include <array>
#include <atomic>
#include <condition_variable>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "needle_sim/calibration/force_assimilation.hpp"
#include "needle_sim/calibration/parameter_adoption.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/observables.hpp"
#include "step_frame.hpp"
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

class Simulation;
struct Rigid;


struct AssimilationParameters {
  std::vector<std::string> keys;  // ~assimilation/keys; empty: off (nothing subscribed, no thread)
  double every = 0.5;             // ~assimilation/every [s of simulation time] between estimates
  // Noises (standard deviations); a channel is subscribed when its noise is given (> 0).
  double wrench_noise = std::numeric_limits<double>::quiet_NaN();  // [N], of the axial force
  double tip_noise = std::numeric_limits<double>::quiet_NaN();     // [m], per coordinate
  double target_noise = std::numeric_limits<double>::quiet_NaN();  // [m], per coordinate
  double shape_noise = std::numeric_limits<double>::quiet_NaN();   // [m], per coordinate of each point
  // [m] the arc length between a measured shape's points (~<needle>/measured_shape: the last
  // pose at the tip, each one before it this much further back along the needle)
  double shape_spacing = 5e-4;
  double outlier_gate = 10;       // residual / noise beyond which the estimator rejects a sample
  std::string needle;             // the needle measured ("": the first)
  std::string target;             // the target ~target/measured measures ("": the first)
  // [s] how late a sample may arrive: an estimate uses the samples up to the simulation's
  // time less this (a later one is refused, stale); a stamp more than max_future ahead of the
  // node's clock is refused too (one ahead of a simulation running behind waits for it).
  double max_latency = 0.1;
  double max_future = 0.1;
  // The live simulation takes each consistent estimate of the keys it can (~assimilation/adopt),
  // moving to it over adopt_ramp [s of simulation time].
  bool adopt = true;
  double adopt_ramp = 0.5;
};

class NodeAssimilation {
 public:
  // Refused measurements, by rule (counted; the first of each kind a second is warned).
  enum Rule { NonFinite, Frame, Stale, Future, Shape, kRules };

  // sim_seconds: a ROS time in the simulation's seconds (the node's clock origin). replay:
  // the refits follow the recorded base poses (not the scene's own motion). Subscribes in
  // pnh's namespace. Throws InputError for a needle, target or key the scene lacks.
  NodeAssimilation(ros::NodeHandle pnh, const AssimilationParameters& p, const std::string& scene_file,
                   const std::vector<std::string>& overrides, const Scene& scene, bool replay,
                   const CommandLimits& limits, tf2_ros::Buffer& tf, const std::string& tissue_frame,
                   bool allow_empty_frame, std::function<double(const ros::Time&)> sim_seconds,
                   std::function<ros::Time(double)> ros_time);
  ~NodeAssimilation();

  // The stepping thread, after each step (the simulation's mutex held): the base pose taken
  // (replay), the needle's axis (a wrench's projection), the simulation's time (what samples
  // may be used); wakes the estimator when an estimate is due.
  // An estimate to adopt is taken into the simulation here (its ramp's next value set).
  void afterStep(Simulation& sim, const Observables& obs);
  // ~reset: the session starts again (samples, commands and the estimate forgotten).
  void restart();
  // ~set_target: a target added or moved (its planning position) during the session; the
  // refits from the next one on set it as the live simulation did, and predict it.
  void setTarget(const std::string& name, const Vec3& planned);
  void diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat);
  // The latest estimate's prediction per target (empty before the first; TargetState, the
  // rviz ellipsoid).
  std::vector<TargetPrediction> predictions();

 private:
  using Sample = MeasurementSample;  // channel 0 force, 1 tip, 2 target, 3 shape
  void onWrench(const geometry_msgs::WrenchStamped::ConstPtr& m);
  void onPoint(int channel, const char* topic, const geometry_msgs::PointStamped::ConstPtr& m);  // tip, target
  void onShape(const geometry_msgs::PoseArray::ConstPtr& m);
  // The message's time in simulation seconds and its frame's transform to the tissue frame
  // (the needle's base frame: identity, its x taken as the axial force); false (counted,
  // warned) when its frame has none.
  bool admit(const std_msgs::Header& h, const char* topic, double& t, Rigid& to_tissue);
  void refuse(Rule r, const char* topic, const std::string& why);
  void queue(const Sample& s, const char* topic);  // stale or future: refused
  void worker();
  // The samples taken, merged into rows (one per time) with the data's channels.
  ForceRecord rows(std::vector<Sample> batch) const;
  void publish(const AssimilationCheckpoint& k, const ForceAssimilation& a, long rejected);

  AssimilationParameters p_;
  AssimilationSettings settings_;
  int needle_ = 0, target_ = 0, num_targets_ = 0;
  std::vector<std::string> target_names_;  // the estimate's targets (under mutex_ once running)
  bool replay_ = false;
  tf2_ros::Buffer& tf_;
  std::string tissue_frame_, base_frame_;
  bool allow_empty_frame_ = false;
  std::function<double(const ros::Time&)> sim_seconds_;
  std::function<ros::Time(double)> ros_time_;
  std::array<bool, 4> channels_{};  // force, tip, target, shape subscribed
  double needle_length_ = 0;        // [m] a shape's points beyond it are refused
  std::string units_;
  ros::Publisher estimate_pub_;
  std::vector<ros::Subscriber> subs_;

  // Stops a refit under way (every run at its next step): the node's end, ~reset.
  std::atomic<bool> cancel_{false};
  PiMutex mutex_;  // everything below
  std::condition_variable_any wake_;
  bool stop_ = false;
  long generation_ = 0;            // ~reset moves it: the estimator drops what it had
  double sim_time_ = 0;            // the simulation's time after the last step
  Vec3 axis_ = Vec3::UnitX();      // the measured needle's base axis (tissue frame)
  std::vector<Sample> pending_;    // arrived, not yet handed to the estimator
  double committed_ = -std::numeric_limits<double>::infinity();  // samples up to here were handed over
  std::vector<RecordedCommand> commands_;
  std::vector<TargetEdit> target_edits_;       // this session's ~set_target calls
  std::vector<std::string> scene_target_names_;  // target_names_ at a session's start
  double next_due_ = 0;
  std::array<long, kRules> refused_{};
  std::array<long, kRules> suppressed_{};
  std::array<ros::WallTime, kRules> last_warning_;
  // The estimator's latest state, for diagnostics.
  long estimates_ = 0, failures_ = 0, outliers_ = 0;
  bool consistent_ = true;
  std::string last_failure_;
  double last_t_ = -1, last_wall_ = 0, last_rms_ = 0, last_innovation_ = 0;
  std::vector<double> last_values_, last_stds_;
  // Adoption: the worker leaves an estimate here, the stepping thread takes it (and alone
  // touches adoption_); ~reset clears both.
  std::vector<double> to_adopt_;   // per key (NaN: not to be adopted)
  bool adopt_new_ = false, adopt_clear_ = false;
  std::vector<TargetPrediction> predictions_;
  std::vector<double> in_use_;     // per key: the live simulation's value (NaN: not adoptable)
  long adopted_ = 0;               // estimates adopted
  std::string adopt_failure_;
  std::unique_ptr<ParameterAdoption> adoption_;
  std::thread thread_;
};

}  // namespace needle_sim
