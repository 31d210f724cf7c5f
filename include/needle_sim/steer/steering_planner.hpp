#pragma once
// Steering a bevel-tipped needle to a target (doc/method.md "Steering to a target"): a
// shooting method on the simulator's own prediction. The plan is the classic roll-flip
// manoeuvre: roll the base so that the bevel points towards the target, insert, roll by pi
// at a chosen depth, insert on to a chosen total advance. Its three numbers (a roll
// correction, the flip depth, the total advance) are solved for the tip to reach the target:
// each iteration predicts the plan on a copy of the simulation (sim/prediction.hpp). The
// first prediction, the full arc without a flip, fixes the roll (where the bend really went),
// the advance (the depth reached) and the curvature; then the flip depth is shot for by
// regula falsi on the in-plane miss, started from the kinematic model's flip.
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/sim/prediction.hpp"

namespace needle_sim {

struct SteeringRequest {
  int needle = 0;
  Vec3 target = Vec3::Zero();  // tissue frame [m]
  double speed = 0.01;         // insertion speed of the base [m/s]
  double roll_rate = M_PI;     // base roll rate for the turns [rad/s]
  double dt = 0;               // prediction time step [s] (0: the scene's)
  double tolerance = 2e-4;     // a plan whose predicted tip-target distance is below this is done [m]
  int max_predictions = 8;          // 1 ... 100
  long max_steps = 1000000;         // per prediction (a longer one is refused: InputError)
  PredictionBudget budget;          // for the whole plan: every prediction's (PredictionStopped)
};

// One prediction of the search.
struct SteeringIterate {
  double roll = 0, flip_depth = 0, advance = 0;  // the plan's numbers
  Vec3 tip = Vec3::Zero();                       // predicted final tip
  double distance = 0;                           // to the target [m]
  double ms = 0;                                 // the prediction's wall time
  double resumed_at = 0;  // it started from an earlier prediction's checkpoint this long after now [s] (0: from now)
  int steps_run = 0;      // steps simulated (fewer than the plan's when resumed)
};

struct SteeringPlan {
  double roll = 0;        // absolute base roll for the first leg [rad] (pose convention)
  double flip_depth = 0;  // base advance at which it rolls by pi [m]; >= advance: no flip
  double advance = 0;     // total base advance [m]
  InsertionPlan plan;     // the waypoints (time from now), for predictInsertion or the node
  Vec3 tip = Vec3::Zero();  // predicted final tip position
  double distance = 0;      // predicted tip-target distance [m]
  bool reached = false;     // distance <= tolerance
  double kappa = 0;         // the fitted path curvature [1/m]
  std::vector<SteeringIterate> iterations;
  double ms = 0;
};

// The waypoints of a roll-flip plan from the needle's commanded pose now.
InsertionPlan rollFlipPlan(const Simulation& live, const SteeringRequest& req, double roll, double flip_depth,
                           double advance);

// Throws InputError (key "steer.<field>") before any work for a request that cannot be
// planned: no such needle, a symmetric tip, a target outside the tissue or not ahead of the
// tip, a non-positive speed; NumericalError when a prediction fails.
SteeringPlan planSteering(const Simulation& live, const SteeringRequest& req);

}  // namespace needle_sim
