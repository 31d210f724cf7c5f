#include "needle_sim/sim/prediction.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <sstream>

#include "needle_sim/core/error.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/tip_speed.hpp"
#include "needle_sim/core/stopwatch.hpp"

namespace needle_sim {

namespace {

// A sample from the simulation's observables (the same numbers the recorder and the node
// report).
PredictionSample sampleOf(const Simulation& sim, double t, int needle, bool target_error) {
  if (target_error && sim.numTargets() > 0) sim.targetErrors();
  const Observables o = observe(sim);
  PredictionSample s;
  s.t = t;
  for (const auto& tg : o.targets) {
    s.targets.push_back(tg.position);
    s.tip_distances.push_back(tg.tip_distances[needle]);
    if (target_error)
      s.target_error_bounds.push_back(tg.has_error ? tg.error_bound : std::numeric_limits<double>::quiet_NaN());
  }
  for (const auto& n : o.needles) {
    s.tips.push_back(n.tip);
    s.base_forces.push_back(n.holder_force);
  }
  return s;
}

// Every check before any work: a plan that cannot run changes nothing and costs nothing.
// (Whether a plan is safe for a robot, the limits, is the command guard's business.)
long requireRunnable(const Simulation& live, const InsertionPlan& plan, long max_steps, double& dt, double& duration) {
  if (plan.needle < 0 || plan.needle >= live.numNeedles())
    throw InputError("", "predict.needle", "no needle " + std::to_string(plan.needle) + " (the scene has " +
                                               std::to_string(live.numNeedles()) + ")");
  double prev = -1;
  for (size_t i = 0; i < plan.waypoints.size(); ++i) {
    const auto& [t, p] = plan.waypoints[i];
    const std::string key = "predict.waypoints[" + std::to_string(i) + "]";
    if (!std::isfinite(t) || t < 0) throw InputError("", key + ".time", "must be finite and >= 0");
    if (t <= prev) throw InputError("", key + ".time", "times must increase strictly");
    prev = t;
    if (!p.position.allFinite()) throw InputError("", key + ".position", "must be finite");
    if (!p.direction.allFinite() || std::abs(p.direction.norm() - 1) > 1e-6)
      throw InputError("", key + ".direction", "must be a finite unit vector");
    if (!std::isfinite(p.roll)) throw InputError("", key + ".roll", "must be finite");
  }
  dt = plan.dt == 0 ? live.dt() : plan.dt;
  if (!(dt > 0) || !std::isfinite(dt)) throw InputError("", "predict.dt", "must be positive and finite (or 0: the scene's)");
  if (!std::isfinite(plan.duration) || plan.duration < 0)
    throw InputError("", "predict.duration", "must be finite and >= 0");
  if (!std::isfinite(plan.sample_period) || plan.sample_period < 0)
    throw InputError("", "predict.sample_period", "must be finite and >= 0");
  duration = plan.duration > 0 ? plan.duration : (plan.waypoints.empty() ? 0.0 : plan.waypoints.back().first);
  if (!(duration > 0)) throw InputError("", "predict.duration", "nothing to simulate: no duration and no waypoint after now");
  const double steps = std::ceil(duration / dt - 1e-9);
  if (steps > static_cast<double>(max_steps)) {
    std::ostringstream m;
    m << duration << " s at dt " << dt << " s is " << steps << " steps, more than the limit of " << max_steps;
    throw InputError("", "predict.duration", m.str());
  }
  return static_cast<long>(steps);
}

// The plan's commanded poses up to time t (from now) must be the checkpoint's: both
// piecewise linear, so comparing at every keyframe of either up to t, and at t, suffices.
void requireSameBeginning(const Simulation& live, const InsertionPlan& plan, double dt, const PredictionCheckpoint& cp) {
  const double now = live.time();
  const BaseTrajectory& had = cp.sim->needle(plan.needle).trajectory();
  BaseTrajectory wants = had;
  wants.replaceFrom(now, dt, plan.waypoints);
  std::vector<double> times{now, now + cp.t};
  for (const auto& [t, p] : had.keyframesAfter(now - 1)) times.push_back(t);
  for (const auto& [t, p] : wants.keyframesAfter(now - 1)) times.push_back(t);
  for (double t : times) {
    if (t > now + cp.t) continue;
    const BasePose a = had.pose(t), b = wants.pose(t);
    if ((a.position - b.position).norm() > 1e-12 || (a.direction - b.direction).norm() > 1e-12 ||
        std::abs(a.roll - b.roll) > 1e-12) {
      std::ostringstream m;
      m << "the plan commands another pose than the checkpoint's at " << t - now << " s from now, before the checkpoint ("
        << cp.t << " s): " << (a.position - b.position).norm() << " m, " << std::abs(a.roll - b.roll) << " rad apart";
      throw InputError("", "predict.resume", m.str());
    }
  }
}

}  // namespace

Prediction predictInsertion(const Simulation& live, const InsertionPlan& plan, long max_steps,
                            const PredictionReuse& reuse, const PredictionBudget& budget) {
  double dt = 0, duration = 0;
  const long steps = requireRunnable(live, plan, max_steps, dt, duration);
  const PredictionCheckpoint* cp = reuse.resume;
  if (cp) {
    if (!cp->sim || cp->step < 1 || cp->step >= steps || std::abs(cp->sim->time() - live.time() - cp->t) > 1e-9 * dt ||
        cp->sim->dt() != dt)
      throw InputError("", "predict.resume", "the checkpoint is not from a prediction of this state at this time step");
    requireSameBeginning(live, plan, dt, *cp);
  }
  Prediction out;
  auto t0 = steadyNow();
  Simulation sim(cp ? *cp->sim : live);
  out.copy_ms = msSince(t0);
  t0 = steadyNow();
  if (dt != sim.dt()) sim.setTimeStep(dt);
  const double now = live.time();
  // The plan replaces the needle's commands from now on; the other needles hold what they
  // were commanded (a copy of their trajectories).
  sim.needle(plan.needle).trajectory().replaceFrom(now, dt, plan.waypoints);
  double next = plan.sample_period;
  if (cp) {
    out.samples = cp->samples;
    next = cp->next_sample;
  } else {
    out.samples.push_back(sampleOf(sim, 0.0, plan.needle, plan.target_error));
  }
  out.max_dofs = sim.numDofs();
  TipSpeedMeter tip_speed;
  tip_speed.observe(sim);  // the tips of now (or of the checkpoint)
  if (cp) {
    out.max_tip_speed = cp->max_tip_speed;
    out.max_tip_speed_t = cp->max_tip_speed_t;
  }
  std::vector<double> wanted = reuse.checkpoint_times;
  std::sort(wanted.begin(), wanted.end());
  size_t w = 0;
  const long first = cp ? cp->step + 1 : 1;
  for (long k = first; k <= steps; ++k) {
    const bool cancelled = budget.cancelled && budget.cancelled();
    if (cancelled || steadyNow() >= budget.deadline) {
      std::ostringstream m;
      m << (cancelled ? "cancelled" : "stopped by " + budget.deadline_name) << " after " << msSince(budget.since) / 1000
        << " s of wall time, at " << sim.time() - now << " s of the plan's " << duration << " s (step " << k - 1
        << " of " << steps << ")";
      throw PredictionStopped(m.str());
    }
    const StepStats& st = sim.step();  // NumericalError propagates: the caller reports it
    out.totals.accumulate(st);
    out.mesh_changes += st.mesh_changed;
    out.max_dofs = std::max(out.max_dofs, sim.numDofs());
    const double t = sim.time() - now;
    tip_speed.observe(sim);
    if (tip_speed.speed(plan.needle) > out.max_tip_speed) {
      out.max_tip_speed = tip_speed.speed(plan.needle);
      out.max_tip_speed_t = t;
    }
    if (k == steps || t >= next - 1e-9 * dt) {
      out.samples.push_back(sampleOf(sim, t, plan.needle, plan.target_error));
      while (next <= t + 1e-9 * dt) next += plan.sample_period > 0 ? plan.sample_period : dt;
    }
    bool keep = false;
    while (w < wanted.size() && wanted[w] <= t + 1e-9 * dt) keep = true, ++w;
    if (keep && k < steps)
      out.checkpoints.push_back(
          {k, t, std::make_shared<const Simulation>(sim), out.samples, next, out.max_tip_speed, out.max_tip_speed_t});
  }
  out.steps = static_cast<int>(steps);
  out.steps_run = static_cast<int>(steps - first + 1);
  out.run_ms = msSince(t0);
  return out;
}

}  // namespace needle_sim
