#pragma once
// Predicting an insertion plan: "where will the target and the tip be, and what will the
// holder feel, if this needle follows this plan from now?", the question of a planner or a
// model-predictive controller. The plan runs on a deep copy of the simulation (bodies,
// factors, constraints, adaptive mesh), so the live simulation is not touched and the
// prediction starts from exactly its state; it may step with a coarser time step than the
// live run (implicit Euler is unconditionally stable), which is what makes it faster than
// real time; `needle_sim predict --compare` reports what the coarser step costs in accuracy.
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

struct Prediction {
  std::vector<PredictionSample> samples;  // the first is the current state (t = 0)
  int steps = 0;
  int max_dofs = 0;
  double copy_ms = 0, run_ms = 0;  // copying the simulation, simulating the plan
  StepStats totals;                // phases summed over the steps (where run_ms goes)
  int mesh_changes = 0;
};

// Throws InputError (key "predict.<field>") for a plan that cannot run (a needle out of
// range, non-finite or non-increasing waypoint times, non-finite poses, a negative dt,
// nothing to simulate, more than max_steps steps), before any work; NumericalError when the
// predicted run fails (the live simulation is unaffected either way).
Prediction predictInsertion(const Simulation& live, const InsertionPlan& plan, long max_steps = 1000000);

}  // namespace needle_sim
