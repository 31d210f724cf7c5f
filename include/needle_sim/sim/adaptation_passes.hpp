#pragma once
// When and where the mesh adapts (doc/method.md, "Refinement and coarsening", "Passes in the
// background"). A pass estimates, marks and refines or coarsens the forest for the scene's
// estimator; it runs every `every_steps` steps and at once on a contact event. On dynamic
// steps it may be deferred: with estimate_delay the pass itself (the goal-oriented one too)
// runs on a background thread
// from a copy of its step's state and its decision is taken up `estimate_delay` later (or
// sooner, waiting for it, when a touch or puncture needs the mesh now); with rebuild_delay a
// change's body is built in the background and switched to `rebuild_delay` after the
// decision, at a step boundary. Results are those of passes on the stepping thread with the
// same switch steps (Adaptivity tests).
//
// Threading contract: from startPass() until its decision is made, the background thread
// owns the forest, the volume fractions (AdaptiveTissue::lend) and the SPR fits
// (EnergyErrorEstimator::lend); it gives them back just before it publishes the decision and
// touches nothing of the simulation's afterwards (it goes on building the new body from
// values it owns). The stepping thread reaches them only after settle(), takePass() or the
// copy constructor, which wait for the decision; their accessors throw std::logic_error
// otherwise. A build reads the scene and the frozen brain shift only.
#include <functional>
#include <future>
#include <memory>
#include <vector>

#include "needle_sim/adapt/error_estimator.hpp"
#include "needle_sim/core/step_stats.hpp"
#include "needle_sim/sim/adaptive_tissue.hpp"
#include "needle_sim/sim/target_error_estimator.hpp"

namespace needle_sim {

// Background work so far (reported in summary.json's adaptivity section).
struct AdaptationCounters {
  long deferred_rebuilds = 0;      // mesh changes built in the background
  long rebuild_waits = 0;          // ... whose switch had to wait for the build
  long background_passes = 0;      // passes run on a background thread
  long pass_waits = 0;             // ... whose decision had to be waited for
  long passes_after_decision = 0;  // passes due while a decision was pending, started at its step
  long ahead_marked = 0;           // elements marked for lying ahead of a tip (lookahead)
};

// The clock the schedule counts in: steps done, the step dt last changed at, dt.
struct StepClock {
  long step = 0, step_base = 0;
  double dt = 0;
};

class AdaptationPasses {
 public:
  // estimator: the scene's (the energy estimate, or goal-oriented indicators); background
  // passes use the energy estimator's SPR fits (goal-oriented ones also a GoalPass, given by
  // setGoalPasses; without, they stay on the stepping thread). points: the constraint points' rest positions now (their elements' compliance
  // columns are built with a new body).
  AdaptationPasses(const AdaptivitySettings& settings, AdaptiveTissue& tissue, EnergyErrorEstimator& energy,
                   ErrorEstimator& estimator, bool goal, std::function<std::vector<Vec3>()> points);
  // For a copy of the simulation (its parts): pending work is copied finished, to be taken
  // up at the same steps.
  AdaptationPasses(const AdaptationPasses& other, AdaptiveTissue& tissue, EnergyErrorEstimator& energy,
                   ErrorEstimator& estimator, std::function<std::vector<Vec3>()> points);
  AdaptationPasses(const AdaptationPasses&) = delete;
  AdaptationPasses& operator=(const AdaptationPasses&) = delete;
  ~AdaptationPasses();
  // AdaptivitySettings::lookahead: the rest-configuration points on the tips' paths ahead,
  // taken on the stepping thread when a pass starts (none: no refinement ahead).
  void setAhead(std::function<std::vector<Vec3>()> ahead) { ahead_ = std::move(ahead); }
  // Goal-oriented passes off the stepping thread: `start` makes a pass's GoalPass at its step
  // (on the stepping thread), `adopt` takes up its targets' estimates at the decision.
  void setGoalPasses(std::function<std::shared_ptr<GoalPass>()> start, std::function<void(const GoalPass&)> adopt) {
    goal_start_ = std::move(start);
    goal_adopt_ = std::move(adopt);
  }

  // After a step that may adapt (dynamic, or with needles): takes up a pending decision or
  // switch due now, and runs a pass when one is due. signature: the constraint counts and
  // states; states: the needles' insertion states (a change means touch or puncture).
  void afterStep(const StepClock& clock, long signature, long states, bool dynamic, StepStats& stats);
  // A pass now (after a deferred change switched first); defer: it may run in the background
  // or build its change there.
  void adaptNow(const StepClock& clock, bool defer, StepStats& stats);
  // One estimate + mark + refine/coarsen of the forest with the scene's estimator (no rebuild).
  AdaptationResult pass();
  // Takes up pending work at once (before a scripted refinement).
  void flush(StepStats& stats);
  // Waits for a background pass's decision (build: and for its body).
  void settle(bool build = false) const;

  bool passPending() const { return pending_pass_ != nullptr; }
  bool rebuildPending() const { return pending_rebuild_ != nullptr; }
  // A build or a pass still being computed (a copy would wait for it).
  bool working() const;
  const AdaptationCounters& counters() const { return counters_; }

  // Tests: every background build and every background pass's decision takes at least this
  // long (late background work).
  static void setDelayForTesting(double ms);

 private:
  struct PassDecision;
  struct PendingRebuild;
  struct PendingPass;
  void startRebuild(const StepClock& clock);
  void finishRebuild(StepStats& stats);
  void startPass(const StepClock& clock);
  void takePass(StepStats& stats);
  long lagSteps(double delay, double dt) const;

  const AdaptivitySettings settings_;
  AdaptiveTissue& tissue_;
  EnergyErrorEstimator& energy_;
  ErrorEstimator& estimator_;
  bool goal_;
  std::function<std::vector<Vec3>()> points_;
  std::function<std::vector<Vec3>()> ahead_;
  std::function<std::shared_ptr<GoalPass>()> goal_start_;
  std::function<void(const GoalPass&)> goal_adopt_;
  std::vector<Vec3> ahead() const { return ahead_ ? ahead_() : std::vector<Vec3>{}; }
  std::unique_ptr<PendingRebuild> pending_rebuild_;
  std::unique_ptr<PendingPass> pending_pass_;
  AdaptationCounters counters_;
  long contact_signature_ = 0;  // constraint counts and states at the last step
  long contact_states_ = 0;     // the needles' states (touch, puncture) at the last step
  bool pass_due_ = false;       // a pass waits for a deferred mesh change
};

}  // namespace needle_sim
