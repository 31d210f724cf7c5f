#pragma once
// Parameters of error-controlled adaptivity (scene section `adaptivity`). Absent section:
// no estimator, no marking, no cost.
#include <string>
#include <vector>

namespace needle_sim {

struct AdaptivitySettings {
  // spr: the energy-norm SPR estimate drives the mesh; goal: the named targets' displacement
  // errors (goal_estimator.hpp) until each bound is below goal_tolerance.
  enum class Estimator { Spr, Goal } estimator = Estimator::Spr;
  std::vector<std::string> goal_targets;  // names of the scene's targets
  double goal_tolerance = 0;              // [m]
  enum class Marking { Max, Bulk } marking = Marking::Max;
  double theta = 0.3;       // max rule: eta_e >= theta max eta; bulk: fraction of sum eta^2
  int max_level = 2;        // refinement levels above the scene's grid
  int max_dofs = 0;         // budget on all tissue DOFs (0: none)
  double tolerance = 0.0;   // relative estimate eta / |sigma_h|_E below which nothing is refined
  int every_steps = 1;      // estimate (and adapt) every this many steps
  // Dynamic steps: a changed mesh's tissue body (pattern, factor, compliance columns) is built
  // on a background thread, and the simulation moves to it this long after the decision
  // [s of simulated time, rounded to whole steps of the current dt, at least one], at a step
  // boundary (0: at once, on the stepping thread). Doc: method.md, "Refinement and
  // coarsening", deferred mesh changes.
  double rebuild_delay = 0;
  // Dynamic steps with the spr estimator: the pass itself (estimate, marking, the new forest)
  // runs on a background thread from a copy of the pass's state, and its decision is taken up
  // this long after the pass [s, whole steps, at least one; at most rebuild_delay] or sooner,
  // waiting for it, when another pass falls due (0: on the stepping thread). The results are
  // those of a pass on the stepping thread. Doc: method.md, "Refinement and coarsening".
  double estimate_delay = 0;
  bool coarsen = false;
  double theta_coarsen = 0.05;  // merge 8 children when sqrt(sum eta_c^2) < theta_coarsen max eta ...
  int coarsen_after = 3;        // ... at this many consecutive estimates (hysteresis)
};

// A static solve on an adaptive mesh (a load step, the brain shift) alternates solve and
// adaptation pass until the mesh stays as it is, at most this many passes.
constexpr int kMaxStaticAdaptationPasses = 6;

}  // namespace needle_sim
