#pragma once
// Predicting an insertion plan: "where will the target and the tip be, and what will the
// holder feel, if this needle follows this plan from now?", the question of a planner or a
// model-predictive controller. The plan runs on a deep copy of the simulation (bodies,
// factors, constraints, adaptive mesh), so the live simulation is not touched and the
// prediction starts from exactly its state; it may step with a coarser time step than the
// live run (implicit Euler is unconditionally stable), which is what makes it faster than
// real time; `needle_sim predict --compare` reports what the coarser step costs in accuracy.
#include <chrono>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

struct InsertionPlan {
  int needle = 0;                                      // the needle that follows the plan
  std::vector<std::pair<double, BasePose>> waypoints;  // (time from now [s], base pose)
  double duration = 0;       // simulated time from now [s]; 0: until the last waypoint
  double dt = 0;             // time step [s]; 0: the live simulation's
  double sample_period = 0;  // spacing of the samples [s]; 0: every step
  bool target_error = false; // a goal-oriented error bound of each target at each sample
};

// One sample of the predicted run; vectors are per target / per needle, in the live
// simulation's order.
struct PredictionSample {
  double t = 0;                   // from now [s]
  std::vector<Vec3> targets;      // target positions
  std::vector<Vec3> tips;         // needle tip positions
  std::vector<Vec3> base_forces;  // force each needle exerts on its holder (-NeedleBody::baseForce)
  std::vector<double> tip_distances;  // per target: distance to the planned needle's tip
  std::vector<double> target_error_bounds;  // per target, with InsertionPlan::target_error (NaN: failed)
};

// The predicted state part way through a plan, kept to run another plan from it: plans that
// agree up to its time (a shooting method's iterates sharing their first leg, e.g. the
// steering planner's flip depths) need not simulate that part again.
struct PredictionCheckpoint {
  long step = 0;                            // steps from now
  double t = 0;                             // time from now [s]
  std::shared_ptr<const Simulation> sim;    // the predicted state then
  std::vector<PredictionSample> samples;    // the samples up to it
  double next_sample = 0;                   // when the next sample is due [s from now]
  double max_tip_speed = 0, max_tip_speed_t = 0;  // Prediction's, up to it
};

struct Prediction {
  std::vector<PredictionSample> samples;  // the first is the current state (t = 0)
  int steps = 0;                          // all of the plan's, including those a checkpoint saved
  int steps_run = 0;                      // simulated by this call
  int max_dofs = 0;
  // The planned needle's largest tip speed over the predicted steps [m/s] (step to step, at
  // the prediction's dt: sim/tip_speed.hpp) and when [s from now]: a snap-back as the needle
  // leaves the tissue shows here before the plan is sent.
  double max_tip_speed = 0, max_tip_speed_t = 0;
  double copy_ms = 0, run_ms = 0;  // copying the simulation, simulating the plan
  StepStats totals;                // phases summed over the steps run (where run_ms goes)
  int mesh_changes = 0;
  std::vector<PredictionCheckpoint> checkpoints;  // those asked for (PredictionReuse)
};

// Reusing work between predictions of plans that share a beginning.
struct PredictionReuse {
  // Start from this checkpoint (made by a prediction from the same live state) instead of
  // from now. The plan must command the same base poses as the checkpoint's up to its time
  // (checked, to 1e-12: InputError "predict.resume" otherwise); the result is then that of
  // the whole prediction, up to rounding.
  const PredictionCheckpoint* resume = nullptr;
  // Keep a checkpoint at the first step at or after each of these times from now (each a
  // deep copy of the simulation: memory, and about as long to make as a step).
  std::vector<double> checkpoint_times;
};

// Stopping a prediction before its end (the node: ~predict_max_wall, its shutdown, ~reset):
// checked before every step; a prediction stopped so throws PredictionStopped. A planner
// making several predictions (planSteering) passes one budget to all of them.
struct PredictionBudget {
  std::chrono::steady_clock::time_point since = std::chrono::steady_clock::now();  // the request's start
  std::chrono::steady_clock::time_point deadline = std::chrono::steady_clock::time_point::max();
  std::string deadline_name;              // what set the deadline, for the message (e.g. "~predict_max_wall = 5 s")
  std::function<bool()> cancelled;        // true: stop now (may be empty)
};

// A prediction stopped by its budget: the message says why, after how much wall time and how
// far the plan had been simulated.
class PredictionStopped : public std::runtime_error {
 public:
  explicit PredictionStopped(const std::string& what) : std::runtime_error(what) {}
};

// Throws InputError (key "predict.<field>") for a plan that cannot run (a needle out of
// range, non-finite or non-increasing waypoint times, non-finite poses, a negative dt,
// nothing to simulate, more than max_steps steps), before any work; NumericalError when the
// predicted run fails; PredictionStopped when its budget runs out or it is cancelled (the
// live simulation is unaffected in every case).
Prediction predictInsertion(const Simulation& live, const InsertionPlan& plan, long max_steps = 1000000,
                            const PredictionReuse& reuse = {}, const PredictionBudget& budget = {});

}  // namespace needle_sim
