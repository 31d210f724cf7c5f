#pragma once
// The ROS face of needle_sim: one class built from (nh, private_nh), shared by the node
// (needle_sim_node) and the nodelet (needle_sim/SimulatorNodelet). No physics here: it reads
// its parameters, turns messages into core commands (checked by the core's CommandGuard),
// steps the core Simulation on a worker thread paced by a ros::Timer (which follows /clock
// under /use_sim_time), and sends what the core's observables say from an output thread.
// Every topic, service and action is in the node's private namespace; the interface (names,
// types, parameters with defaults, frames, conventions) is doc/ros_api.md.
//
// The implementation is split by concern: simulator_ros.cpp (set-up, pacing, stepping,
// diagnostics), command_input.cpp (poses, plans, tf commands, frames), services.cpp (reset,
// set_target, predict), steer_service.cpp (steer), display_outputs.cpp (cloud, surface,
// markers, path, tf frames), insert_action.cpp (the InsertNeedle action), and the helpers
// beside them.
#include <ros/ros.h>

#include <array>
#include <chrono>
#include <atomic>
#include <functional>
#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <diagnostic_updater/diagnostic_updater.h>
#include <geometry_msgs/PoseStamped.h>
#include <needle_sim/NeedleTrajectory.h>
#include <needle_sim/PredictInsertion.h>
#include <needle_sim/SteerToTarget.h>
#include <needle_sim/SetTarget.h>
#include <ros/callback_queue.h>
#include <std_srvs/Trigger.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_listener.h>
#include <trajectory_msgs/MultiDOFJointTrajectory.h>

#include "needle_sim/command/command_guard.hpp"
#include "needle_sim/needle/holder_wrench.hpp"
#include "needle_sim/sim/command_pipeline.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/prediction.hpp"
#include "needle_sim/sim/preflight.hpp"
#include "needle_sim/sim/realtime_schedule.hpp"
#include "needle_sim/core/run_statistics.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "needle_sim/sim/tip_speed.hpp"
#include "needle_sim/core/pi_mutex.hpp"

namespace needle_sim {

struct NodeParameters;
class OutputQueue;
class DisplayOutputs;
class InsertAction;
class LimitsReconfigure;
class NodeAssimilation;
struct Rigid;
struct StepFrame;

class SimulatorRos {
 public:
  // Throws InputError (scene file, key or ~parameter, problem) when it cannot start.
  SimulatorRos(ros::NodeHandle nh, ros::NodeHandle pnh);
  ~SimulatorRos();

  // For the action and the services (same thread rules as the callbacks): a plan goes to the
  // core's command pipeline, which checks and takes it at the next step boundary.
  using Plan = CommandPipeline::Plan;
  void queuePlan(Plan plan);
  // Stops a needle where it is now (the action's preemption).
  void holdNeedle(int needle);

 private:
  friend class InsertAction;
  // --- set-up and stepping (simulator_ros.cpp)
  void load();                  // (re)builds the simulation; sim_mutex_ held or not yet shared
  void onTimer(const ros::TimerEvent&);
  void worker();
  // The wall-clock pace: the stepping thread sleeps until its next step is due, one wake per
  // step (the timer and its hand-over cost a second wake and its latency).
  void pacedWorker();
  void setStepperPriority();  // ~realtime_priority
  void restartAfterClockJump(const char* what);  // the clock went back: warn, reset
  bool self_paced_ = false;
  void applyCommands();         // at a step boundary, sim_mutex_ held
  void stepOnce();              // sim_mutex_ held
  void publishStep(double ms);  // sim_mutex_ held
  // ~<needle>/wrench between the steps of a scene slower than ~wrench_rate (the wall-clock
  // pace): after each step the stepping thread tabulates each needle's wrench, the step's and
  // every 1/~wrench_rate over the next two steps (the step's model, needle/holder_wrench.hpp,
  // with the base where its commanded motion has it then); wrenchLoop, the topic's one sender
  // then, sends the step's row when it comes (stamped as its status) and, every
  // 1/~wrench_rate of wall time, the row of the time elapsed since (also while the next step
  // is computed, or late), stamped at that row's time after the step.
  void tabulateWrenches(const ros::Time& stamp);  // sim_mutex_ held, after a step (its status's stamp)
  void wrenchLoop();
  struct WrenchTable {
    long seq = 0;  // the tabulating step's count
    std::chrono::steady_clock::time_point made;
    ros::Time stamp;  // the step's, as its status: row j is stamped j periods later
    std::vector<std::string> frames;
    std::vector<std::pair<Vec3, Vec3>> step;  // [needle]: the step's own force and moment
    std::vector<std::vector<std::pair<Vec3, Vec3>>> ticks;  // [j - 1][needle]: force, moment at t0 + j period
  };
  std::vector<HolderWrenchExtrapolation> wrench_models_;  // per needle (sim_mutex_); cleared by load()
  double wrench_period_ = 0;                              // 0: none between steps; set before threads start
  PiMutex wrench_mutex_;                               // wrench_table_, wrench_stop_
  std::condition_variable_any wrench_cv_;
  WrenchTable wrench_table_;
  bool wrench_stop_ = false;
  std::thread wrench_thread_;
  void diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat);
  // Goal-oriented error bounds of the targets, off the stepping thread: every
  // ~target_error_period the worker copies the simulation (sim_mutex_ held) and this thread
  // estimates on the copy; the next steps' observables carry the result.
  void errorLoop();
  void updateTargetErrors();  // sim_mutex_ held
  double simSeconds(const ros::Time& t) const;  // ROS time -> simulation time (queue_mutex_ held)
  void sendStep(const StepFrame& f);            // on the output thread
  void restartClock(const ros::Time& now);      // queue_mutex_ held
  // --- command input (command_input.cpp)
  void subscribeCommands();
  // (caller: the publisher's caller id, from the connection header: the source for rule owner)
  void onPose(int needle, const geometry_msgs::PoseStamped::ConstPtr& m, const std::string& caller);
  void onTrajectory(int needle, const needle_sim::NeedleTrajectory::ConstPtr& m, const std::string& caller);
  void onMultiDof(int needle, const trajectory_msgs::MultiDOFJointTrajectory::ConstPtr& m, const std::string& caller);
  void lookupTfCommands();
  // The transform from a message's frame to the tissue frame; false (counted, warned) when
  // the frame is empty and not allowed, or tf has no transform.
  bool toTissue(const std::string& frame, const ros::Time& stamp, const std::string& source, Rigid& out);
  void admit(int needle, const PoseCommand& c, const std::string& source);  // c.source: who sent it
  void warnRule(GuardRule rule, const std::string& source, const std::string& why);
  PiMutex warn_mutex_;
  std::array<ros::WallTime, kGuardRules> last_warning_;  // per rule (throttled to 1 Hz), warn_mutex_
  std::array<unsigned long, kGuardRules> suppressed_{};  // warnings held back since
  // --- services (services.cpp)
  bool onReset(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res);
  bool onSetTarget(needle_sim::SetTarget::Request& req, needle_sim::SetTarget::Response& res);
  bool onPredict(needle_sim::PredictInsertion::Request& req, needle_sim::PredictInsertion::Response& res);
  // (steer_service.cpp)
  bool onSteer(needle_sim::SteerToTarget::Request& req, needle_sim::SteerToTarget::Response& res,
               const std::string& caller);
  int needleIndex(const std::string& name) const;  // -1: none; "" is the first
  // Why a service refuses a request whose `field` is in a frame toTissue could not take.
  std::string frameRefusal(const std::string& field, const std::string& frame) const;

  ros::NodeHandle nh_, pnh_;
  std::unique_ptr<NodeParameters> params_;
  Scene scene_;
  // Every command reaches the simulation through it (sim/command_pipeline.hpp).
  std::unique_ptr<CommandPipeline> pipeline_;
  CommandGuard& guard() const { return pipeline_->guard(); }
  std::unique_ptr<OutputQueue> out_;
  std::unique_ptr<DisplayOutputs> display_;
  std::unique_ptr<InsertAction> action_;
  std::unique_ptr<LimitsReconfigure> reconfigure_;
  // Measurements in, the online estimate out (node_assimilation.hpp); null without ~assimilation/keys.
  std::unique_ptr<NodeAssimilation> assimilation_;

  PiMutex sim_mutex_;  // guards sim_ and everything the stepping thread changes
  std::unique_ptr<Simulation> sim_;
  std::shared_ptr<const ObservableNames> names_;
  Observables obs_;
  std::string failure_;
  bool commanded_ = false;  // a command was taken since the start (state waiting before)
  int primary_target_ = 0;
  // Step times: percentiles over the last kStepWindow steps, maximum and steps over dt since
  // the start or ~reset.
  static constexpr size_t kStepWindow = 10000;
  RunStatistics step_ms_{0, kStepWindow};
  double publish_ms_ = 0;
  std::deque<std::pair<ros::WallTime, double>> rtf_window_;  // (wall, sim time)
  ros::WallTime last_display_;
  std::atomic<double> sim_time_now_{0.0};
  std::atomic<int> realtime_priority_{0};
  int steppingPriority() const;  // the SCHED_FIFO priority the stepping thread asks for (0: none)
  // The automatic priority is left once the simulation is this far behind the clock [s]: a
  // FIFO thread stepping back to back would hold a core (a scene too heavy for the machine,
  // a sanitizer's build).
  static constexpr double kFifoMaxLag = 1.0;
  void leaveRealtimePriority(double behind);  // on the stepping thread  // the stepping thread's SCHED_FIFO priority (0: none)  // for commands in ~as_fast_as_possible mode
  uint64_t diag_rejected_ = 0, diag_limited_ = 0;  // at the last diagnostics
  // Steps whose constraint solve missed its tolerance (lifetime; ~reset keeps it), and the
  // count at the last diagnostics.
  uint64_t unconverged_steps_ = 0, diag_unconverged_ = 0;
  double constraint_residual_ = 0;  // of the last step
  // The tips' speeds, every step (~max_tip_speed: warned, diagnostics tip_speed).
  TipSpeedMeter tip_speed_;
  double maxTipSpeed() const;  // the threshold in force
  void watchTipSpeed();        // after each step, sim_mutex_ held
  void diagnoseTipSpeed(diagnostic_updater::DiagnosticStatusWrapper& stat);
  std::vector<double> tip_speed_peak_;     // per needle, the largest since the last diagnostics
  std::vector<uint64_t> tip_speed_over_;   // per needle, lifetime: steps above ~max_tip_speed
  std::vector<uint64_t> diag_tip_over_;    // ... at the last diagnostics
  ros::WallTime last_tip_warning_;
  double last_tip_warned_speed_ = 0;
  unsigned long tip_warnings_suppressed_ = 0;
  double predict_max_dt_ = 0;  // ~predict_max_dt, resolved against the scene's dt

  PiMutex queue_mutex_;  // schedule_, origin_, stop_
  RealtimeSchedule schedule_;
  ros::Time origin_;  // ROS time of step 0 (zero: not started)
  std::condition_variable_any wake_;
  bool stop_ = false;

  std::unique_ptr<tf2_ros::Buffer> tf_buffer_;
  std::unique_ptr<tf2_ros::TransformListener> tf_listener_;
  std::vector<std::string> base_frames_;  // tf commands
  std::vector<ros::Time> tf_last_stamp_;
  std::vector<char> tf_missing_;  // per base: no transform at the last lookup (counted once per outage)
  ros::Timer timer_, diag_timer_;
  std::vector<ros::Subscriber> command_subs_;
  ros::Publisher status_pub_, target_pub_, target_state_pub_;
  std::vector<ros::Publisher> wrench_pubs_;
  std::unique_ptr<diagnostic_updater::Updater> updater_;
  // The diagnostics timer's callback runs under this and not once the node goes (a stopped
  // timer's callback may still be under way on a spinner thread).
  PiMutex diag_mutex_;
  bool diag_stopped_ = false;
  ros::ServiceServer reset_srv_, set_target_srv_, predict_srv_, steer_srv_;
  ros::CallbackQueue predict_queue_;  // predictions (~predict, ~steer) take their own thread
  // Predictions and plans (services.cpp): their budget (~predict_max_wall; cancelled when the
  // epoch moves: ~reset, the node's end), and what they cost (diagnostics).
  PredictionBudget predictionBudget(long generation);
  void predictionDone(double wall_s, const char* outcome);  // "ok", "stopped", "cancelled", "preempted", "failed"
  std::atomic<long> predict_epoch_{0};
  // Requests in order of arrival: the predictions' two threads take turns (one prediction at
  // a time, predict_turn_mutex_), and a newer request supersedes the one under way or waiting
  // (~predict_preempt): its budget's cancel test sees the generation move on.
  std::atomic<long> predict_generation_{0};
  std::mutex predict_turn_mutex_;
  bool superseded(long generation) const;
  std::mutex predict_cost_mutex_;
  struct PredictionCost {
    long requests = 0, stopped = 0, cancelled = 0, preempted = 0;
    double last_s = 0, max_s = 0, total_s = 0;
  } predict_cost_;
  std::unique_ptr<ros::AsyncSpinner> predict_spinner_;
  // The pre-flight at start (~preflight_wall; sim/preflight.hpp): whether the scene keeps
  // real time here, in the log and in diagnostics for the node's lifetime. Set before any
  // thread starts, read-only after.
  PreflightResult preflight_;
  bool preflight_run_ = false;
  std::thread thread_;
  PiMutex error_mutex_;  // error_job_, errors_latest_, errors_step_, error_busy_, error_stop_
  std::condition_variable_any error_cv_;
  std::unique_ptr<Simulation> error_job_;
  std::vector<TargetError> errors_latest_;
  long errors_step_ = -1;
  bool error_busy_ = false, error_stop_ = false;
  double last_error_time_ = -1e300;  // simulation time of the last copy taken (sim_mutex_)
  // No copy before this (the estimates' duty cycle, ~target_error_duty; error_mutex_).
  std::chrono::steady_clock::time_point next_error_wall_{};
  long error_estimates_ = 0;          // estimates finished (error_mutex_; diagnostics)
  double error_wall_s_total_ = 0, error_wall_s_max_ = 0;  // their wall time [s]
  std::thread error_thread_;
};

}  // namespace needle_sim
