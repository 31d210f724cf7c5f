#pragma once
// Parameters of error-controlled adaptivity (scene section `adaptivity`). Absent section:
// no estimator, no marking, no cost.
#include <string>

#include "needle_sim/core/parameters.hpp"
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
  // Dynamic steps: the pass itself (estimate, with the goal estimator its targets' duals too,
  // marking, the new forest) runs on a background thread from a copy of the pass's state, and
  // its decision is taken up
  // this long after the pass [s, whole steps, at least one; at most rebuild_delay] or sooner,
  // waiting for it, when another pass falls due (0: on the stepping thread). The results are
  // those of a pass on the stepping thread. Doc: method.md, "Refinement and coarsening".
  double estimate_delay = 0;
  // Refinement ahead of the tip (doc/method.md, "Refinement ahead of the tip"): every pass also
  // refines to max_level the elements each needle's tip will reach within this time [s] by
  // its trajectory's base motion (the entry point before the touch), first within the DOF
  // budget, and merges none of them while they lie ahead. 0: off.
  double lookahead = 0;
  bool coarsen = false;
  double theta_coarsen = 0.05;  // merge 8 children when sqrt(sum eta_c^2) < theta_coarsen max eta ...
  int coarsen_after = 3;        // ... at this many consecutive estimates (hysteresis)

  // The `adaptivity` section's value keys (core/parameters.hpp); goal.targets is read by the
  // scene loader, which also checks the rules that tie keys together.
  static const Parameters<AdaptivitySettings>& parameters() {
    using S = AdaptivitySettings;
    static const Parameters<S> p =
        Parameters<S>()
            .choice("estimator", [](S& s) -> Estimator& { return s.estimator; }, {"spr", "goal"},
                    "spr: the energy-norm SPR estimate (Zienkiewicz–Zhu) drives the mesh; goal: the displacement-error indicators of the targets in `goal.targets` do ([method.md](method.md#error-on-target-motion))")
            .real("goal.tolerance", [](S& s) -> double& { return s.goal_tolerance; }, "m", Range::nonNegative(),
                  "with `estimator: goal`, required and > 0: refine while a controlled target's error bound is above this; below it, only coarsening")
            .choice("marking", [](S& s) -> Marking& { return s.marking; }, {"max", "bulk"},
                    "max: η_e ≥ θ·max η (the paper's); bulk: Dörfler, θ of Σ η²")
            .real("theta", [](S& s) -> double& { return s.theta; }, "", Range::openClosed(0, 1), "θ",
                  true)
            .integer("max_level", [](S& s) -> int& { return s.max_level; }, Range::closed(0, 6),
                     "refinement levels above the scene's grid")
            .integer("max_dofs", [](S& s) -> int& { return s.max_dofs; }, Range::closed(0, 100000000),
                     "budget on all tissue DOFs (0: none)")
            .real("tolerance", [](S& s) -> double& { return s.tolerance; }, "", Range::nonNegative(),
                  "nothing is refined while η / ‖σ_h‖_E ≤ tolerance")
            .integer("every_steps", [](S& s) -> int& { return s.every_steps; }, Range::closed(1, 1000000000),
                     "estimate and adapt every N steps (and at once on every contact event)")
            .real("rebuild_delay", [](S& s) -> double& { return s.rebuild_delay; }, "s", Range::closed(0, 10),
                  "dynamic steps: build a changed mesh's body in the background and move to it this long after the decision (whole steps of the dt in use, at least one); 0: at once, on the stepping thread ([method.md](method.md#refinement-and-coarsening))")
            .real("estimate_delay", [](S& s) -> double& { return s.estimate_delay; }, "s", Range::closed(0, 10),
                  "dynamic steps, at most `rebuild_delay`: run each pass (with the `goal` estimator, its targets' estimates too) on a background thread from a copy of its step's state and take its decision up this long after it; the same run as passes on the stepping thread, without their cost on it; 0: on the stepping thread")
            .real("lookahead", [](S& s) -> double& { return s.lookahead; }, "s", Range::closed(0, 10),
                  "refine to `max_level`, first, the elements each needle's tip will reach within this time by its trajectory (the path ahead, the entry point before the touch), so that deferred mesh changes do not lag the tip; 0: off ([method.md](method.md#refinement-ahead-of-the-tip))")
            .flag("coarsen.enabled", [](S& s) -> bool& { return s.coarsen; }, "merge children back; coarsening runs only with `enabled: true`")
            .real("coarsen.theta_coarsen", [](S& s) -> double& { return s.theta_coarsen; }, "", Range::open(0, 1),
                  "merge 8 children when √(Σ η_c²) < theta_coarsen·max η (with `max` marking and coarsening: < θ/2) ...")
            .integer("coarsen.after", [](S& s) -> int& { return s.coarsen_after; }, Range::closed(1, 1000000),
                     "... at this many consecutive passes (hysteresis)");
    return p;
  }
};

// A static solve on an adaptive mesh (a load step, the brain shift) alternates solve and
// adaptation pass until the mesh stays as it is, at most this many passes.
constexpr int kMaxStaticAdaptationPasses = 6;

}  // namespace needle_sim
