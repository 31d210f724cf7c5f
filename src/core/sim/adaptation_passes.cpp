#include "needle_sim/sim/adaptation_passes.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <mutex>
#include <thread>

#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/stopwatch.hpp"

namespace needle_sim {

namespace {
std::atomic<double> g_delay_ms{0.0};

void testDelay() {
  const double delay = g_delay_ms;
  if (delay > 0) std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(delay));
}
}  // namespace

void AdaptationPasses::setDelayForTesting(double ms) { g_delay_ms = ms; }

struct AdaptationPasses::PassDecision {
  AdaptationResult result;
  ErrorEstimate estimate;  // of the pass's step
  std::shared_ptr<const GoalPass> goal;  // goal-oriented: the targets' estimates made with it
  double estimate_ms = 0, mark_refine_ms = 0;  // on the background thread
};

struct AdaptationPasses::PendingRebuild {
  std::shared_future<std::shared_ptr<AdaptiveTissue::Prepared>> job;
  long switch_step = 0;
};

struct AdaptationPasses::PendingPass {
  long step = 0;         // whose state it estimates
  long take_step = 0;    // its decision is taken up here at the latest
  long switch_step = 0;  // a change is switched to here (as if decided at `step`)
  std::shared_future<std::shared_ptr<const PassDecision>> decision;
  // The same decision, also handed over under a mutex. ThreadSanitizer once reported the copy
  // of its estimate after the future's get() as a race with the writing on the pass's thread
  // (CI, 2026-12-05; not reproduced in a dozen runs since): a mutex's hand-over is one it sees; the
  // future stays what the stepping thread waits on and what carries the pass's error.
  struct Slot {
    std::mutex m;
    std::shared_ptr<const PassDecision> d;
  };
  std::shared_ptr<Slot> slot;
  std::shared_future<std::shared_ptr<AdaptiveTissue::Prepared>> build;  // null after no change
};

namespace {
// A finished future holding a copy of a prepared body (or null).
std::shared_future<std::shared_ptr<AdaptiveTissue::Prepared>> readyCopy(
    const std::shared_ptr<AdaptiveTissue::Prepared>& p) {
  std::promise<std::shared_ptr<AdaptiveTissue::Prepared>> ready;
  ready.set_value(p ? AdaptiveTissue::copyPrepared(*p) : nullptr);
  return ready.get_future().share();
}
}  // namespace

AdaptationPasses::AdaptationPasses(const AdaptivitySettings& settings, AdaptiveTissue& tissue,
                                   EnergyErrorEstimator& energy, ErrorEstimator& estimator, bool goal,
                                   std::function<std::vector<Vec3>()> points)
    : settings_(settings), tissue_(tissue), energy_(energy), estimator_(estimator), goal_(goal), points_(std::move(points)) {}

AdaptationPasses::AdaptationPasses(const AdaptationPasses& o, AdaptiveTissue& tissue, EnergyErrorEstimator& energy,
                                   ErrorEstimator& estimator, std::function<std::vector<Vec3>()> points)
    : settings_(o.settings_),
      tissue_(tissue),
      energy_(energy),
      estimator_(estimator),
      goal_(o.goal_),
      points_(std::move(points)),
      counters_(o.counters_),
      contact_signature_(o.contact_signature_),
      contact_states_(o.contact_states_),
      pass_due_(o.pass_due_) {
  o.settle(true);
  if (o.pending_rebuild_) {
    // The copy switches at the same step to a copy of the same body (finished here, so that
    // both step alike whatever the thread's timing).
    pending_rebuild_ = std::make_unique<PendingRebuild>(*o.pending_rebuild_);
    pending_rebuild_->job = readyCopy(o.pending_rebuild_->job.get());
  }
  if (o.pending_pass_) {
    // The same decision (finished), taken up at the same step; a body it built is copied.
    pending_pass_ = std::make_unique<PendingPass>(*o.pending_pass_);
    pending_pass_->build = readyCopy(o.pending_pass_->build.get());
  }
}

AdaptationPasses::~AdaptationPasses() {
  // A background build reads the scene: it finishes before the simulation goes.
  if (pending_rebuild_ && pending_rebuild_->job.valid()) pending_rebuild_->job.wait();
  settle(true);
}

namespace {
template <class Future>
bool running(const Future& f) {
  return f.valid() && f.wait_for(std::chrono::seconds(0)) != std::future_status::ready;
}
}  // namespace

bool AdaptationPasses::working() const {
  return (pending_rebuild_ && running(pending_rebuild_->job)) ||
         (pending_pass_ && (running(pending_pass_->decision) || running(pending_pass_->build)));
}

long AdaptationPasses::lagSteps(double delay, double dt) const {
  return delay > 0 ? std::max(1L, std::lround(delay / dt)) : 0;
}

void AdaptationPasses::settle(bool build) const {
  if (!pending_pass_) return;
  pending_pass_->decision.wait();
  if (build && pending_pass_->build.valid()) pending_pass_->build.wait();
}

AdaptationResult AdaptationPasses::pass() {
  const ErrorEstimate& indicators = estimator_.localErrors();
  return tissue_.adaptation()->adapt(indicators, estimator_.refinementWanted(), ahead());
}

void AdaptationPasses::flush(StepStats& stats) {
  if (pending_pass_) takePass(stats);
  if (pending_rebuild_) finishRebuild(stats);
}

void AdaptationPasses::adaptNow(const StepClock& clock, bool defer, StepStats& stats) {
  // A pass estimates the mesh the last pass decided on: a deferred change switches first.
  flush(stats);
  if (defer && lagSteps(settings_.estimate_delay, clock.dt) > 0 && (!goal_ || goal_start_)) {
    const auto t0 = steadyNow();
    startPass(clock);
    stats.adapted = true;
    stats.estimate_ms = msSince(t0);  // this thread's share: the copies
    return;
  }
  const auto t0 = steadyNow();
  estimator_.localErrors();
  const auto t1 = steadyNow();
  const AdaptationResult r = pass();
  counters_.ahead_marked += r.ahead;
  const auto t2 = steadyNow();
  const bool deferred = r.changed && defer && lagSteps(settings_.rebuild_delay, clock.dt) > 0;
  if (deferred) startRebuild(clock);
  else if (r.changed) tissue_.rebuild(true);
  const auto t3 = steadyNow();
  stats.adapted = true;
  stats.mesh_changed = stats.mesh_changed || (r.changed && !deferred);
  stats.refined = r.refined;
  stats.coarsened = r.coarsened;
  stats.estimate_ms = msBetween(t0, t1);
  stats.mark_refine_ms = msBetween(t1, t2);
  stats.rebuild_ms += msBetween(t2, t3);
}

void AdaptationPasses::startRebuild(const StepClock& clock) {
  // On this thread: the state carried to the new mesh (a transfer, cheap), its volume
  // fractions (cached per cell), and where the constraint points are. The rest, which is
  // most of a rebuild (DOF map, assembly pattern, factor, compliance columns, the organ's
  // embedding), on a background thread, from values it owns.
  MeshAdaptation& forest = *tissue_.adaptation();
  auto pending = std::make_unique<PendingRebuild>();
  pending->switch_step = clock.step + lagSteps(settings_.rebuild_delay, clock.dt);
  AdaptiveTissue::MeshChange change = tissue_.forestMesh(forest);
  VecX x = forest.transfer(tissue_.body().positions()), v = forest.transfer(tissue_.body().velocities());
  tissue_.body().holdFactorRefresh(true);  // the build gets the second core (the DBS switch waited for it)
  const AdaptiveTissue* tissue = &tissue_;  // prepare() reads the scene and the frozen brain shift only
  pending->job = std::async(std::launch::async,
                            [tissue, h = clock.dt, change = std::move(change), x = std::move(x), v = std::move(v),
                             points = points_(), retired = tissue_.takeRetired()]() mutable {
                              lowerThisThreadPriority();
                              nameThisThread("ns_rebuild");
                              retired.reset();  // the body the last switch replaced: freed here
                              auto p = tissue->prepare(std::move(change), x, v, true, h, points);
                              testDelay();
                              return p;
                            })
                     .share();
  pending_rebuild_ = std::move(pending);
  ++counters_.deferred_rebuilds;
}

void AdaptationPasses::finishRebuild(StepStats& stats) {
  const auto t0 = steadyNow();
  PendingRebuild& pr = *pending_rebuild_;
  if (pr.job.wait_for(std::chrono::seconds(0)) != std::future_status::ready) ++counters_.rebuild_waits;
  std::shared_ptr<AdaptiveTissue::Prepared> p = pr.job.get();
  tissue_.switchTo(*p, true, true);
  pending_rebuild_.reset();
  stats.mesh_changed = true;
  stats.rebuild_ms += msSince(t0);
}

void AdaptationPasses::startPass(const StepClock& clock) {
  // On this thread: copies of what the pass reads (positions, velocities, the rotation
  // guesses the estimate's polar decompositions start from, the constraint points). The
  // fits and the forest are lent to the background thread until its decision.
  const SprEstimator* spr = &energy_.spr();
  MeshAdaptation* forest = tissue_.adaptation();
  auto pp = std::make_unique<PendingPass>();
  pp->step = clock.step;
  const long estimate_lag = lagSteps(settings_.estimate_delay, clock.dt);
  pp->take_step = clock.step + estimate_lag;
  pp->switch_step = clock.step + std::max(lagSteps(settings_.rebuild_delay, clock.dt), estimate_lag);
  std::promise<std::shared_ptr<const PassDecision>> decided;
  pp->decision = decided.get_future().share();
  pp->slot = std::make_shared<PendingPass::Slot>();
  const VecX* reference = energy_.reference();  // changes only at a switch
  AdaptiveTissue* tissue = &tissue_;
  EnergyErrorEstimator* energy = &energy_;
  const TissueBody& body = tissue_.body();
  std::shared_ptr<GoalPass> goal = goal_ ? goal_start_() : nullptr;
  tissue_.lend();
  energy_.lend();
  pp->build = std::async(
                  std::launch::async,
                  [tissue, energy, spr, forest, reference, h = clock.dt, decided = std::move(decided), slot = pp->slot,
                   retired = tissue_.takeRetired(), x = VecX(body.positions()), v = VecX(body.velocities()),
                   guesses = body.model().rotationGuesses(), points = points_(), ahead = ahead(),
                   goal = std::move(goal)]() mutable
                  -> std::shared_ptr<AdaptiveTissue::Prepared> {
                    lowerThisThreadPriority();
                    nameThisThread("ns_adapt");
                    retired.reset();  // here, not on the stepping thread
                    AdaptiveTissue::MeshChange change;
                    VecX xt, vt;
                    auto giveBack = [&] {
                      tissue->giveBack();
                      energy->giveBack();
                    };
                    try {
                      auto d = std::make_shared<PassDecision>();
                      const auto t0 = steadyNow();
                      d->estimate = spr->estimate(x, reference, &guesses);
                      const ErrorEstimate* marking = &d->estimate;
                      bool refine = true;
                      if (goal) {
                        marking = &goal->run(*spr, x, guesses, d->estimate);
                        refine = goal->refinementWanted();
                        d->goal = goal;
                      }
                      const auto t1 = steadyNow();
                      d->estimate_ms = msBetween(t0, t1);
                      d->result = forest->adapt(*marking, refine, ahead);
                      if (d->result.changed) {
                        change = tissue->forestMesh(*forest);
                        xt = forest->transfer(x);
                        vt = forest->transfer(v);
                      }
                      d->mark_refine_ms = msSince(t1);
                      testDelay();  // tests: a late pass
                      const bool changed = d->result.changed;
                      giveBack();
                      {
                        std::lock_guard<std::mutex> lock(slot->m);
                        slot->d = d;
                      }
                      decided.set_value(std::move(d));  // from here on, nothing of the simulation's is touched
                      if (!changed) return nullptr;
                    } catch (...) {
                      giveBack();
                      decided.set_exception(std::current_exception());
                      return nullptr;
                    }
                    auto p = tissue->prepare(std::move(change), xt, vt, true, h, points);
                    testDelay();
                    return p;
                  })
                  .share();
  pending_pass_ = std::move(pp);
  ++counters_.background_passes;
}

void AdaptationPasses::takePass(StepStats& stats) {
  PendingPass& pp = *pending_pass_;
  if (pp.decision.wait_for(std::chrono::seconds(0)) != std::future_status::ready) ++counters_.pass_waits;
  pp.decision.get();  // rethrows the pass's error
  std::shared_ptr<const PassDecision> d;
  {
    std::lock_guard<std::mutex> lock(pp.slot->m);
    d = pp.slot->d;
  }
  energy_.adopt(d->estimate);  // the last one made (of the pass's step, not of this one)
  if (d->goal && goal_adopt_) goal_adopt_(*d->goal);
  counters_.ahead_marked += d->result.ahead;
  stats.refined += d->result.refined;
  stats.coarsened += d->result.coarsened;
  if (d->result.changed) {
    auto pending = std::make_unique<PendingRebuild>();
    pending->switch_step = pp.switch_step;
    pending->job = pp.build;
    tissue_.body().holdFactorRefresh(true);
    pending_rebuild_ = std::move(pending);
    ++counters_.deferred_rebuilds;
  }
  pending_pass_.reset();
}

void AdaptationPasses::afterStep(const StepClock& clock, long signature, long states, bool dynamic, StepStats& stats) {
  // A deferred mesh change switches at its step, at this step boundary. A pass due while
  // one is being built, or at the switch, waits for the first step on the new mesh: its
  // estimate must be of a state computed there, not of one carried over.
  // A background pass's decision is taken up at its step: a change becomes the deferred
  // change a pass on this thread would have started, with the same switch step. A pass that
  // falls due before it, at a needle's touch or puncture, takes it up at once (waiting for
  // it if need be): the mesh must follow the puncture without delay (deferred to the
  // decision's step, the adaptive phantom's probes moved by 3.4 % of their largest
  // displacement from those of passes on the stepping thread). A pass due at a new or
  // released constraint point starts at the decision's step, after it: waiting there and
  // then for the background thread (a new shaft point a step after the regular pass) made
  // the adaptive phantom's slowest steps, 1-2.7 ms against a median of 0.3. So does a
  // goal-oriented pass due at a touch or puncture: its pass takes 25-60 ms (a factorisation
  // of K), and waiting for it at dbs_goal's touch, puncture and insertion (three steps in a
  // row) made steps of 30 ms in the node.
  bool switched = false;
  if (pending_pass_ && clock.step >= pending_pass_->take_step) takePass(stats);
  if (pending_rebuild_ && clock.step >= pending_rebuild_->switch_step) {
    finishRebuild(stats);
    switched = true;
  }
  const bool was_due = pass_due_;
  pass_due_ = pass_due_ || (clock.step - clock.step_base) % settings_.every_steps == 0 || signature != contact_signature_;
  if (pass_due_ && pending_pass_ && states != contact_states_ && !goal_) takePass(stats);
  if (pass_due_ && !was_due && pending_pass_) ++counters_.passes_after_decision;
  if (pass_due_ && !pending_pass_ && !pending_rebuild_ && !switched) {
    pass_due_ = false;
    adaptNow(clock, dynamic, stats);
  }
  contact_signature_ = signature;
  contact_states_ = states;
}

}  // namespace needle_sim
