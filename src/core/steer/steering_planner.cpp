#include "needle_sim/steer/steering_planner.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/fem/embedded_point.hpp"

namespace needle_sim {

namespace {

// The flip depth whose S ends `lateral` off the axis (per unit curvature) after a base
// advance A, in the kinematic (constant-curvature) model: an arc to s, the opposite arc
// after it, s^2/2 + s (A - s) - (A - s)^2/2 = lateral; A when even the full arc falls short.
double flipFor(double lateral_per_kappa, double A) {
  const double disc = 0.5 * A * A - lateral_per_kappa;
  if (disc <= 0) return A;
  return std::clamp(A - std::sqrt(disc), 0.0, A);
}

}  // namespace

InsertionPlan rollFlipPlan(const Simulation& live, const SteeringRequest& req, double roll, double flip_depth,
                           double advance) {
  const BasePose p0 = live.needle(req.needle).trajectory().pose(live.time());
  InsertionPlan plan;
  plan.needle = req.needle;
  plan.dt = req.dt;
  double t = 0;
  // No leg shorter than a step: a waypoint sooner than that would be moved to it when the
  // plan is installed (BaseTrajectory::replaceFrom), changing the legs' speeds.
  const double step = req.dt > 0 ? req.dt : live.dt();
  auto at = [&](double dt_leg, double s, double r) {
    t += std::max(dt_leg, step);
    plan.waypoints.push_back({t, BasePose{p0.position + p0.direction * s, p0.direction, r}});
  };
  const double s = std::clamp(flip_depth, 0.0, advance);
  at(std::abs(roll - p0.roll) / req.roll_rate, 0, roll);  // turn the bevel first
  if (s > 0) at(s / req.speed, s, roll);
  if (s < advance) {
    at(M_PI / req.roll_rate, s, roll + M_PI);
    at((advance - s) / req.speed, advance, roll + M_PI);
  }
  at(0.05, advance, plan.waypoints.back().second.roll);  // settle
  return plan;
}

SteeringPlan planSteering(const Simulation& live, const SteeringRequest& req) {
  const auto t0 = steadyNow();
  if (req.needle < 0 || req.needle >= live.numNeedles())
    throw InputError("", "steer.needle", "no needle " + std::to_string(req.needle));
  const NeedleBody& nd = live.needle(req.needle);
  if (!nd.bevel().enabled)
    throw InputError("", "steer.needle", "needle '" + nd.name() + "' has a symmetric tip: only a bevel tip steers (needle.bevel)");
  if (!live.interaction()) throw InputError("", "steer", "the scene has no needle-tissue interaction");
  if (!(req.speed > 0) || !std::isfinite(req.speed)) throw InputError("", "steer.speed", "must be > 0");
  if (!(req.roll_rate > 0) || !std::isfinite(req.roll_rate)) throw InputError("", "steer.roll_rate", "must be > 0");
  if (!(req.tolerance > 0)) throw InputError("", "steer.tolerance", "must be > 0");
  if (req.max_predictions < 1 || req.max_predictions > 100)
    throw InputError("", "steer.max_predictions", "must be in [1, 100]");
  if (!req.target.allFinite()) throw InputError("", "steer.target", "must be finite");
  // The target must be tissue (rest position; the planner runs before the insertion).
  live.embedPoint(req.target, "steer.target", "the target");

  const BasePose p0 = nd.trajectory().pose(live.time());
  const Vec3 a = p0.direction.normalized();
  const Vec3 tip0 = nd.tipPosition();
  const Vec3 d = req.target - tip0;
  const double depth = d.dot(a);
  if (!(depth > 0)) {
    std::ostringstream m;
    m << "the target is not ahead of the tip along the needle's axis (depth " << depth << " m)";
    throw InputError("", "steer.target", m.str());
  }
  const Vec3 lat = d - depth * a;
  // The bevel's direction now and the roll that points it at the target.
  Vec3 b = nd.bevelDirection();
  b = (b - a.dot(b) * a).normalized();
  const Vec3 u = lat.norm() > 1e-12 ? Vec3(lat.normalized()) : b;
  const Vec3 w = a.cross(u);
  double roll = p0.roll + std::atan2(b.cross(u).dot(a), b.dot(u));

  SteeringPlan best;
  best.distance = std::numeric_limits<double>::infinity();
  // Checkpoints along the first leg (before the flip) of the predictions at one roll: a plan
  // with the same roll shares that leg up to its own flip, so it starts from the deepest
  // checkpoint before it and simulates only the rest (the result is the same, to rounding).
  // Kept for one roll at a time, every 1/16 of the advance (a few tens of deep copies).
  std::vector<PredictionCheckpoint> checkpoints;
  double checkpoint_roll = std::numeric_limits<double>::quiet_NaN();
  auto predict = [&](double r, double s, double A) {
    const auto t1 = steadyNow();
    InsertionPlan plan = rollFlipPlan(live, req, r, s, A);
    if (!(r == checkpoint_roll)) checkpoints.clear(), checkpoint_roll = r;
    const double turned = plan.waypoints.front().first;                     // the bevel turned to r
    const double leg_end = s > 0 ? plan.waypoints[1].first : turned;         // the flip starts (or the advance ends)
    PredictionReuse reuse;
    for (const auto& c : checkpoints)
      if (c.t <= leg_end) reuse.resume = &c;
    const double spacing = std::max(A / 16, 10 * (req.dt > 0 ? req.dt : live.dt()) * req.speed) / req.speed;
    for (double tc = turned + spacing; tc < leg_end; tc += spacing)
      if (!reuse.resume || tc > reuse.resume->t) reuse.checkpoint_times.push_back(tc);
    Prediction p = predictInsertion(live, plan, req.max_steps, reuse, req.budget);
    const double resumed_at = reuse.resume ? reuse.resume->t : 0.0;  // before `checkpoints` grows
    for (auto& c : p.checkpoints) checkpoints.push_back(std::move(c));
    std::sort(checkpoints.begin(), checkpoints.end(), [](const auto& a, const auto& b) { return a.t < b.t; });
    SteeringIterate it{r, s, A, p.samples.back().tips[req.needle], 0, 0};
    it.distance = (it.tip - req.target).norm();
    it.ms = msSince(t1);
    it.resumed_at = resumed_at;
    it.steps_run = p.steps_run;
    best.iterations.push_back(it);
    if (it.distance < best.distance) {
      best.roll = r, best.flip_depth = s, best.advance = A;
      best.plan = plan;
      best.tip = it.tip;
      best.distance = it.distance;
    }
    return it;
  };

  // 1. The full arc towards the target (no flip), as deep as the target: the farthest the
  //    tip gets sideways. It fits the curvature, corrects the roll for where the bend really
  //    went (out of the target's plane) and the advance for the depth the tip fell short.
  double A = depth;
  SteeringIterate it = predict(roll, A, A);
  auto reach = [&](const SteeringIterate& p) { return (p.tip - tip0).dot(u); };
  best.kappa = 2 * reach(it) / std::pow(std::max((it.tip - tip0).dot(a), 1e-6), 2);
  double g_hi = reach(it) - lat.norm();  // in-plane overshoot of the full arc
  // (An out-of-plane miss far below the tolerance, e.g. rounding in a symmetric scene, is
  // left alone: the same roll lets the next predictions start from this one's checkpoints.)
  const double out_of_plane = (req.target - it.tip).dot(w);
  if (best.kappa > 0 && std::abs(reach(it)) > 1e-9 && std::abs(out_of_plane) > 0.01 * req.tolerance)
    roll += std::atan2(out_of_plane, reach(it));
  A = std::max(A + (req.target - it.tip).dot(a), 1e-4);
  // 2. Beyond its reach the full arc is the plan. Otherwise the flip depth s in [0, A] is
  //    found by regula falsi (Illinois) on the in-plane overshoot g(s), which grows with s
  //    (a later flip bends farther): g(A) is the full arc's, g(0) the kinematic model's
  //    (-kappa A^2 / 2 - offset, the bend the other way), the first guess the model's flip.
  if (best.kappa > 0 && g_hi > 0 && best.distance > req.tolerance) {
    double lo = 0, hi = A, g_lo = -0.5 * best.kappa * A * A - lat.norm();
    int side = 0;
    double s = flipFor(lat.norm() / best.kappa, A);
    while (static_cast<int>(best.iterations.size()) < req.max_predictions) {
      it = predict(roll, s, A);
      if (best.distance <= req.tolerance) break;
      const double g = reach(it) - lat.norm();
      if (g > 0) {
        hi = s, g_hi = g;
        if (side == 1) g_lo *= 0.5;
        side = 1;
      } else {
        lo = s, g_lo = g;
        if (side == -1) g_hi *= 0.5;
        side = -1;
      }
      s = hi - g_hi * (hi - lo) / (g_hi - g_lo);
      A = std::max(A + (req.target - it.tip).dot(a), s);  // the S's own depth
    }
  }
  best.reached = best.distance <= req.tolerance;
  best.ms = msSince(t0);
  return best;
}

}  // namespace needle_sim
