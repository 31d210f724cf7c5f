#include "needle_sim/calibration/force_calibration.hpp"

#include <nlopt.h>
#include <yaml-cpp/yaml.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <future>

#include "needle_sim/contact/centre_line.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_keys.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/scene/scene_overrides.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

namespace {

std::string num(double v) {
  char b[40];
  std::snprintf(b, sizeof b, "%.17g", v);
  return b;
}

// The scene's value of a key path (maps by name, lists by index); undefined if absent.
// (yaml-cpp: `n = child` would assign into the tree; reset() rebinds the handle.)
YAML::Node lookup(const YAML::Node& root, const std::string& key) {
  YAML::Node n;
  n.reset(root);
  size_t pos = 0;
  while (pos <= key.size()) {
    const size_t dot = std::min(key.find('.', pos), key.size());
    const std::string part = key.substr(pos, dot - pos);
    if (!n || !(n.IsMap() || n.IsSequence())) return YAML::Node(YAML::NodeType::Undefined);
    if (n.IsSequence()) {
      char* end = nullptr;
      const long i = std::strtol(part.c_str(), &end, 10);
      if (part.empty() || *end || i < 0 || i >= static_cast<long>(n.size())) return YAML::Node(YAML::NodeType::Undefined);
      n.reset(n[static_cast<size_t>(i)]);
    } else {
      const YAML::Node child = n[part];
      if (!child) return YAML::Node(YAML::NodeType::Undefined);
      n.reset(child);
    }
    pos = dot + 1;
  }
  return n;
}

// The loader's verdict on a value of the key (empty: accepted).
std::string rejects(const CalibrationSettings& s, const std::string& key, double v) {
  std::vector<std::string> sets = s.sets;
  sets.push_back(key + "=" + num(v));
  try {
    loadScene(s.scene, sets);  // the scene's own checks (the start run builds the bodies)
  } catch (const InputError& e) {
    return e.problem();
  }
  return "";
}

double scaleOf(const CalibrationParameter& p) {
  if (std::isfinite(p.scale) && p.scale > 0) return p.scale;
  return std::abs(p.start) > 0 ? std::abs(p.start) : 1.0;
}

}  // namespace

std::vector<std::string> parameterSets(const std::vector<CalibrationParameter>& p, const std::vector<double>& v) {
  std::vector<std::string> out;
  for (size_t i = 0; i < p.size(); ++i) out.push_back(p[i].key + "=" + num(v[i]));
  return out;
}

std::vector<CalibrationParameter> resolveParameters(const CalibrationSettings& s) {
  if (s.parameters.empty()) throw InputError("", "--fit", "no parameter to fit");
  YAML::Node root;
  try {
    root = YAML::LoadFile(s.scene);
  } catch (const YAML::Exception& e) {
    throw InputError(s.scene, "", std::string("cannot read the scene: ") + e.what());
  }
  root = resolveExtends(root, s.scene);
  for (const auto& o : s.sets) applyOverride(root, o, s.scene);
  std::vector<CalibrationParameter> out;
  for (CalibrationParameter p : s.parameters) {
    for (const auto& q : out)
      if (q.key == p.key) throw InputError(s.scene, p.key, "named twice in --fit");
    // Only declared real-valued keys (core/parameters.hpp; `needle_sim keys` lists them).
    const std::optional<ParameterDeclaration> decl = findSceneKey(p.key);
    if (decl && decl->kind != ParameterKind::Real)
      throw InputError(s.scene, p.key,
                       decl->kind == ParameterKind::Integer ? "not a real-valued key (an integer)" : "not a number (a " + decl->type() + ")");
    if (!std::isfinite(p.start)) {
      const YAML::Node n = lookup(root, p.key);
      if (!n || n.IsNull()) {
        // Absent from the file: a key the scene does not know, or an optional one.
        if (!decl) throw InputError(s.scene, p.key, "not a key this scene accepts (`needle_sim keys` lists the value keys)");
        throw InputError(s.scene, p.key, "the scene has no value for it: give its start with --start " + p.key + "=VALUE");
      }
      if (!n.IsScalar()) throw InputError(s.scene, p.key, "not a number (a list or a map): only real-valued keys can be fitted");
      char* end = nullptr;
      const std::string text = n.Scalar();
      p.start = std::strtod(text.c_str(), &end);
      if (end == text.c_str() || *end || !std::isfinite(p.start))
        throw InputError(s.scene, p.key, "not a number ('" + text + "'): only real-valued keys can be fitted");
    }
    if (!decl) throw InputError(s.scene, p.key, "not a declared value key (`needle_sim keys` lists them)");
    // Known to the scene and valid at the start (with every other value as given).
    if (const std::string why = rejects(s, p.key, p.start); !why.empty())
      throw InputError(s.scene, p.key, "the start value " + num(p.start) + " is rejected: " + why);
    // Bounds where not given: the declared range, nudged inward by 1e-3 scales at an open end,
    // within 10 scales of the start. (A key tied to another by a rule, such as inner_radius
    // below radius, needs --bounds.)
    const double sc = scaleOf(p);
    const Range& range = decl->range;
    if (!std::isfinite(p.lower)) {
      p.lower = p.start - 10 * sc;
      if (std::isfinite(range.lo)) p.lower = std::max(p.lower, range.lo_closed ? range.lo : range.lo + 1e-3 * sc);
    }
    if (!std::isfinite(p.upper)) {
      p.upper = p.start + 10 * sc;
      if (std::isfinite(range.hi)) p.upper = std::min(p.upper, range.hi_closed ? range.hi : range.hi - 1e-3 * sc);
    }
    if (!(p.lower < p.upper)) throw InputError(s.scene, p.key, "empty bounds [" + num(p.lower) + ", " + num(p.upper) + "]");
    if (p.start < p.lower || p.start > p.upper)
      throw InputError(s.scene, p.key, "the start " + num(p.start) + " is outside its bounds [" + num(p.lower) + ", " +
                                           num(p.upper) + "]");
    out.push_back(p);
  }
  return out;
}

double residualRoughness(const VecX& fwd, const VecX& bwd) {
  const double size = fwd.norm() + bwd.norm();
  return size > 0 ? (fwd - bwd).norm() / size : 0.0;
}

MeasurementWeights measurementWeights(const CalibrationSettings& s, const ForceRecord& data) {
  const auto check = [](double v, const char* option, const char* what) {
    if (!std::isnan(v) && !(v > 0 && std::isfinite(v)))
      throw InputError("", option, std::string("the ") + what + " must be a positive number");
  };
  check(s.noise, "--noise", "force measurement's noise (standard deviation, N)");
  check(s.tip_noise, "--tip-noise", "tip measurement's noise (standard deviation per coordinate, m)");
  check(s.target_noise, "--target-noise", "target measurement's noise (standard deviation per coordinate, m)");
  check(s.shape_noise, "shape_noise", "shape measurement's noise (standard deviation per coordinate, m)");
  MeasurementWeights w;
  const bool force = data.hasForce(), tip = data.hasTip(), target = data.hasTargets(), shape = data.hasShape();
  if (shape && !(data.shape_spacing > 0 && std::isfinite(data.shape_spacing)))
    throw InputError("", "shape_spacing", "a measured shape needs the spacing of its points, a positive number [m]");
  if (force + tip + target + shape > 1) {
    // Several channels: each weighed by the reference channel's noise over its own.
    const auto need = [](double v, const char* option) {
      if (std::isnan(v))
        throw InputError("", option, "a record of several channels (force, tip, target, shape) needs each one's noise to "
                                     "weigh them: --noise [N], --tip-noise [m], --target-noise [m], the shape's [m]");
    };
    if (force) need(s.noise, "--noise");
    if (tip) need(s.tip_noise, "--tip-noise");
    if (target) need(s.target_noise, "--target-noise");
    if (shape) need(s.shape_noise, "shape_noise");
  }
  if (force) {
    w.noise = s.noise;
  } else if (tip) {
    w.noise = s.tip_noise;
    w.units = "m";
  } else if (target) {
    w.noise = s.target_noise;
    w.units = "m";
  } else {
    w.noise = s.shape_noise;
    w.units = "m";
  }
  if (tip && !std::isnan(w.noise)) w.tip_weight = w.noise / s.tip_noise;
  if (target && !std::isnan(w.noise)) w.target_weight = w.noise / s.target_noise;
  if (shape && !std::isnan(w.noise)) w.shape_weight = w.noise / s.shape_noise;
  return w;
}

SimulatedForce simulateHolderForce(const std::string& scene, const std::vector<std::string>& sets, int needle,
                                   double until, const std::vector<RecordedCommand>* commands, bool target_errors,
                                   const CommandLimits& limits, const std::atomic<bool>* cancel,
                                   const CentreLineRequest& centre_line, const std::vector<TargetEdit>& target_edits) {
  SimulatedForce r;
  Scene sc = loadScene(scene, sets);
  if (needle < 0 || needle >= static_cast<int>(sc.needles.size()))
    throw InputError(scene, "needle", "the scene has no needle " + std::to_string(needle));
  const bool replaying = commands && !commands->empty();
  if (replaying) {
    // The commands drive the needle, and any other needle they command (as in the node,
    // whose commanded needles have no motion of their own).
    sc.needles[needle].motion.clear();
    for (const RecordedCommand& c : *commands)
      if (c.needle >= 0 && c.needle < static_cast<int>(sc.needles.size())) sc.needles[c.needle].motion.clear();
    sc.duration = std::max(until, sc.dt);
  }
  try {
    Simulation::Options so;
    so.target_errors = target_errors;
    Simulation sim(sc, so);
    for (const TargetEdit& e : target_edits) sim.setTarget(e.name, e.planned);
    std::unique_ptr<CommandReplay> replay;
    if (replaying) replay = std::make_unique<CommandReplay>(sim, limits, *commands);
    const BasePose p0 = sim.needle(needle).trajectory().pose(0);
    const long steps = std::min(sc.numSteps(), static_cast<long>(std::ceil(until / sc.dt - 1e-9)) + 1);
    Observables o;
    // The centre line's steps: those within one step of a requested time (the times sorted).
    std::vector<double> times = centre_line.times;
    std::sort(times.begin(), times.end());
    const auto near = [&](double t) {
      if (times.empty()) return true;
      const auto it = std::lower_bound(times.begin(), times.end(), t - sc.dt * (1 + 1e-9));
      return it != times.end() && *it <= t + sc.dt * (1 + 1e-9);
    };
    for (long k = 0; k < steps; ++k) {
      if (cancel && cancel->load(std::memory_order_relaxed)) {
        r.failed = true;
        r.failure = "cancelled";
        return r;
      }
      if (replay) replay->beforeStep(sim);
      sim.step();
      observe(sim, o);
      const BasePose b = sim.needle(needle).trajectory().pose(sim.time());
      r.t.push_back(o.time);
      r.force.push_back(o.needles[needle].axial_force);
      r.tip.push_back(o.needles[needle].tip);
      r.targets.resize(o.targets.size());
      for (size_t j = 0; j < o.targets.size(); ++j) r.targets[j].push_back(o.targets[j].position);
      r.advance.push_back((b.position - p0.position).dot(p0.direction));
      if (centre_line.wanted() && (k == 0 || k + 1 == steps || near(o.time))) {
        // Arc length i spacing back from the tip (rest arc length: the beam barely stretches).
        const NeedleBody& nd = sim.needle(needle);
        const double length = nd.beam().elementLength() * nd.beam().numElements();
        std::vector<Vec3> c(centre_line.points);
        for (size_t i = 0; i < c.size(); ++i)
          c[i] = centreLinePoint(nd, std::max(0.0, length - static_cast<double>(i) * centre_line.spacing)).position;
        r.shape_t.push_back(o.time);
        r.shape.push_back(std::move(c));
      }
      if (!std::isfinite(r.force.back())) throw NumericalError(k, "non-finite holder force");
    }
    for (const TargetObservation& t : o.targets) r.target_end.push_back(t.position);
    if (target_errors)
      for (const TargetError& e : sim.targetErrors())
        r.target_end_bound.push_back(e.valid ? e.component_bound : Vec3::Constant(std::numeric_limits<double>::quiet_NaN()));
  } catch (const NumericalError& e) {
    r.failed = true;
    r.failure = e.what();
  }
  return r;
}

std::vector<Vec3> centreLineAt(const SimulatedForce& f, double x) {
  if (f.shape.empty()) return {};
  if (x <= f.shape_t.front()) return f.shape.front();
  if (x >= f.shape_t.back()) return f.shape.back();
  const size_t i = static_cast<size_t>(std::upper_bound(f.shape_t.begin(), f.shape_t.end(), x) - f.shape_t.begin());
  const double w = (x - f.shape_t[i - 1]) / (f.shape_t[i] - f.shape_t[i - 1]);
  std::vector<Vec3> c(f.shape[i].size());
  for (size_t k = 0; k < c.size(); ++k) c[k] = (1 - w) * f.shape[i - 1][k] + w * f.shape[i][k];
  return c;
}

namespace {

struct Problem {
  const CalibrationSettings* s;
  nlopt_opt opt = nullptr;  // (to stop it when cancelled)
  const ForceRecord* data;
  MeasurementWeights w;
  std::vector<CalibrationParameter> p;
  std::vector<double> scale;
  double until = 0, penalty = 0;
  CentreLineRequest shape;  // the data's shape samples' points and times
  int samples = 0;  // measured samples inside the simulated time
  int evaluations = 0, failed = 0;
  double best = std::numeric_limits<double>::infinity();
  const std::function<void(int, double, const std::vector<double>&)>* progress;

  std::vector<double> values(const double* x) const {
    std::vector<double> v(p.size());
    for (size_t i = 0; i < p.size(); ++i) v[i] = std::clamp(x[i] * scale[i], p[i].lower, p[i].upper);
    return v;
  }
  SimulatedForce run(const std::vector<double>& v) const {
    std::vector<std::string> sets = s->sets;
    for (const auto& o : parameterSets(p, v)) sets.push_back(o);
    try {
      return simulateHolderForce(s->scene, sets, s->needle, until, &s->commands, false, s->limits, s->cancel, shape,
                                 s->target_edits);
    } catch (const InputError& e) {  // a combination the scene rejects: a penalised point
      SimulatedForce f;
      f.failed = true;
      f.failure = e.what();
      return f;
    }
  }
  // Residuals at the measured samples inside the simulated time: the force's, the tip's
  // (three, weighted); with rows and channels, which sample each is.
  // A measured target's residuals are (simulated + offset) - measured, the offset the mean of
  // measured - simulated over its samples (the least-squares offset: profiled out).
  VecX residuals(const SimulatedForce& f, std::vector<int>* rows = nullptr, std::vector<int>* channels = nullptr,
                 std::vector<Vec3>* offsets = nullptr) const {
    std::vector<double> r;
    const bool tip = !data->tip.empty();
    const PointSeries tip_series(tip ? f.tip : std::vector<Vec3>{});
    // Per measured target: the simulation at its samples, and its offset.
    const size_t nt = data->targets.size();
    std::vector<std::vector<Vec3>> at(nt);
    std::vector<Vec3> offset(nt, Vec3::Constant(NAN));
    for (size_t j = 0; j < nt; ++j) {
      if (data->targets[j].empty() || j >= f.targets.size()) continue;
      const PointSeries c(f.targets[j]);
      Vec3 sum = Vec3::Zero();
      int count = 0;
      at[j].assign(data->t.size(), Vec3::Constant(NAN));
      for (size_t i = 0; i < data->t.size(); ++i)
        if (data->t[i] <= until + 1e-12 && data->targets[j][i].allFinite()) {
          at[j][i] = c.at(f.t, data->t[i]);
          sum += data->targets[j][i] - at[j][i];
          ++count;
        }
      if (count) offset[j] = sum / count;
    }
    if (offsets) *offsets = offset;
    for (size_t i = 0; i < data->t.size(); ++i) {
      if (data->t[i] > until + 1e-12) continue;
      if (std::isfinite(data->force[i])) {
        r.push_back(interpolate(f.t, f.force, data->t[i]) - data->force[i]);
        if (rows) rows->push_back(static_cast<int>(i)), channels->push_back(0);
      }
      if (tip && data->tip[i].allFinite()) {
        const Vec3 at_tip = tip_series.at(f.t, data->t[i]);
        for (int k = 0; k < 3; ++k) {
          r.push_back(w.tip_weight * (at_tip[k] - data->tip[i][k]));
          if (rows) rows->push_back(static_cast<int>(i)), channels->push_back(1 + k);
        }
      }
      for (size_t j = 0; j < nt; ++j)
        if (!at[j].empty() && at[j][i].allFinite())
          for (int k = 0; k < 3; ++k) {
            r.push_back(w.target_weight * (at[j][i][k] + offset[j][k] - data->targets[j][i][k]));
            if (rows) rows->push_back(static_cast<int>(i)), channels->push_back(4 + 3 * static_cast<int>(j) + k);
          }
      if (i < data->shape.size() && !data->shape[i].empty()) {
        const std::vector<Vec3> c = centreLineAt(f, data->t[i]);
        for (size_t q = 0; q < data->shape[i].size() && q < c.size(); ++q)
          for (int k = 0; k < 3; ++k) {
            r.push_back(w.shape_weight * (c[q][k] - data->shape[i][q][k]));
            if (rows) rows->push_back(static_cast<int>(i)), channels->push_back(-1);
          }
      }
    }
    return Eigen::Map<const VecX>(r.data(), static_cast<Eigen::Index>(r.size()));
  }
};

double objective(unsigned n, const double* x, double* grad, void* data) {
  (void)n;
  (void)grad;  // BOBYQA is derivative-free
  Problem& pr = *static_cast<Problem*>(data);
  if (pr.s->cancel && pr.s->cancel->load(std::memory_order_relaxed)) {
    nlopt_force_stop(pr.opt);  // (no exception through the C library)
    return pr.penalty;
  }
  const std::vector<double> v = pr.values(x);
  const SimulatedForce f = pr.run(v);
  ++pr.evaluations;
  double cost;
  if (f.failed) {
    ++pr.failed;
    cost = pr.penalty;
  } else {
    cost = pr.residuals(f).squaredNorm();
  }
  pr.best = std::min(pr.best, cost);
  if (*pr.progress) (*pr.progress)(pr.evaluations, std::sqrt(cost / std::max(pr.samples, 1)), v);
  return cost;
}

const char* stopReason(nlopt_result r) {
  switch (r) {
    case NLOPT_SUCCESS: return "success";
    case NLOPT_STOPVAL_REACHED: return "stopval reached";
    case NLOPT_FTOL_REACHED: return "relative change of the cost below its tolerance";
    case NLOPT_XTOL_REACHED: return "relative change of the parameters below xtol_rel";
    case NLOPT_MAXEVAL_REACHED: return "evaluation limit reached";
    case NLOPT_MAXTIME_REACHED: return "time limit reached";
    case NLOPT_ROUNDOFF_LIMITED: return "round-off limited";
    case NLOPT_FORCED_STOP: return "forced stop";
    default: return "failure";
  }
}

}  // namespace

CalibrationResult calibrate(const CalibrationSettings& s, const ForceRecord& data,
                            const std::function<void(int, double, const std::vector<double>&)>& progress) {
  const auto t0 = std::chrono::steady_clock::now();
  CalibrationResult r;
  Problem pr;
  pr.s = &s;
  pr.data = &data;
  pr.progress = &progress;
  pr.w = measurementWeights(s, data);
  pr.p = resolveParameters(s);
  r.parameters = pr.p;
  const Scene sc = loadScene(s.scene, s.sets);
  pr.until = s.commands.empty() ? std::min(sc.duration, data.t.back()) : data.t.back();
  pr.shape = CentreLineRequest::of(data);
  const size_t n = pr.p.size();
  std::vector<double> x(n), lb(n), ub(n), step(n);
  for (size_t i = 0; i < n; ++i) {
    pr.scale.push_back(scaleOf(pr.p[i]));
    x[i] = pr.p[i].start / pr.scale[i];
    lb[i] = pr.p[i].lower / pr.scale[i];
    ub[i] = pr.p[i].upper / pr.scale[i];
    step[i] = std::min(0.25, 0.4 * (ub[i] - lb[i]));
    if (std::isfinite(pr.p[i].initial_step) && pr.p[i].initial_step > 0)
      step[i] = std::min(step[i], std::max(1e-3, pr.p[i].initial_step / pr.scale[i]));
  }
  std::vector<double> start(n);
  for (size_t i = 0; i < n; ++i) start[i] = pr.p[i].start;
  r.start_run = pr.run(start);
  if (r.start_run.failed) {
    if (s.cancel && s.cancel->load()) throw CalibrationCancelled();
    throw NumericalError(0, "the simulation fails at the start values: " + r.start_run.failure);
  }
  const VecX r0 = pr.residuals(r.start_run);
  r.residuals = pr.samples = static_cast<int>(r0.size());
  if (r.residuals < static_cast<int>(n) + 1)
    throw InputError("", "--data", std::to_string(r.residuals) + " measured values fall inside the scene's " +
                                       std::to_string(sc.duration) + " s: at least " + std::to_string(n + 1) +
                                       " are needed for " + std::to_string(n) + " parameters");
  r.rms_start = std::sqrt(r0.squaredNorm() / r.residuals);
  // A failed evaluation costs more than any measurement could be off by.
  std::vector<double> measured;
  for (size_t i = 0; i < data.t.size(); ++i) {
    if (std::isfinite(data.force[i])) measured.push_back(data.force[i]);
    if (!data.tip.empty() && data.tip[i].allFinite())
      for (int k = 0; k < 3; ++k) measured.push_back(pr.w.tip_weight * data.tip[i][k]);
    for (const auto& q : data.targets)
      if (!q.empty() && q[i].allFinite())
        for (int k = 0; k < 3; ++k) measured.push_back(pr.w.target_weight * q[i][k]);
    if (i < data.shape.size())
      for (const Vec3& q : data.shape[i])
        for (int k = 0; k < 3; ++k) measured.push_back(pr.w.shape_weight * q[k]);
  }
  pr.penalty = 100 * std::max(r0.squaredNorm(), Eigen::Map<const VecX>(measured.data(), static_cast<Eigen::Index>(measured.size())).squaredNorm());

  nlopt_opt opt = nlopt_create(NLOPT_LN_BOBYQA, static_cast<unsigned>(n));
  nlopt_set_lower_bounds(opt, lb.data());
  nlopt_set_upper_bounds(opt, ub.data());
  nlopt_set_initial_step(opt, step.data());
  nlopt_set_xtol_rel(opt, s.xtol_rel);
  std::vector<double> xtol_abs(n, 0.0);
  for (size_t i = 0; i < n; ++i)
    if (std::isfinite(pr.p[i].tolerance) && pr.p[i].tolerance > 0) xtol_abs[i] = pr.p[i].tolerance / pr.scale[i];
  nlopt_set_xtol_abs(opt, xtol_abs.data());
  nlopt_set_maxeval(opt, s.max_evaluations);
  nlopt_set_min_objective(opt, objective, &pr);
  pr.opt = opt;
  double cost = 0;
  const nlopt_result res = nlopt_optimize(opt, x.data(), &cost);
  nlopt_destroy(opt);
  if (s.cancel && s.cancel->load()) throw CalibrationCancelled();
  r.stop_reason = stopReason(res);
  if (res < 0 && res != NLOPT_ROUNDOFF_LIMITED && res != NLOPT_FORCED_STOP)
    throw NumericalError(0, std::string("the optimiser failed: ") + r.stop_reason);
  r.values = pr.values(x.data());
  r.evaluations = pr.evaluations;
  r.failed_evaluations = pr.failed;
  r.fitted_run = pr.run(r.values);
  if (r.fitted_run.failed) {  // cancelled after the optimiser stopped: its samples end early
    if (s.cancel && s.cancel->load()) throw CalibrationCancelled();
    throw NumericalError(0, "the simulation fails at the fitted values: " + r.fitted_run.failure);
  }
  const VecX rf = pr.residuals(r.fitted_run, &r.residual_row, &r.residual_channel, &r.target_offsets);
  for (const Vec3& o : r.target_offsets) r.offset_parameters += o.allFinite() ? 3 : 0;
  r.rms = std::sqrt(rf.squaredNorm() / r.residuals);
  r.residuals_fit = rf;

  // Central-difference Jacobian of the residuals at the fit (one-sided at a bound), the runs
  // in parallel; steps of 1 % of each parameter's scale.
  Eigen::MatrixXd J(r.residuals, static_cast<Eigen::Index>(n));
  std::vector<std::function<void()>> jobs;
  std::vector<SimulatedForce> plus(n), minus(n);
  std::vector<double> hp(n), hm(n);
  for (size_t i = 0; i < n; ++i) {
    const double h = 1e-2 * pr.scale[i];
    hp[i] = std::min(h, pr.p[i].upper - r.values[i]);
    hm[i] = std::min(h, r.values[i] - pr.p[i].lower);
    jobs.emplace_back([&, i] {
      std::vector<double> v = r.values;
      v[i] += hp[i];
      plus[i] = pr.run(v);
    });
    jobs.emplace_back([&, i] {
      std::vector<double> v = r.values;
      v[i] -= hm[i];
      minus[i] = pr.run(v);
    });
  }
  const size_t threads = static_cast<size_t>(std::max(1, s.threads));
  // Scenes load on several threads at once here: none may change the BLAS's thread count
  // (Simulation::setSetupThreads) under another's running calls.
  struct NoSetupThreads {
    const int was = Simulation::setupThreads();
    NoSetupThreads() { Simulation::setSetupThreads(0); }
    ~NoSetupThreads() { Simulation::setSetupThreads(was); }
  } no_setup_threads;
  for (size_t k = 0; k < jobs.size(); k += threads) {
    std::vector<std::future<void>> f;
    for (size_t j = k; j < std::min(jobs.size(), k + threads); ++j) f.push_back(std::async(std::launch::async, jobs[j]));
    for (auto& x : f) x.get();
  }
  r.jacobian_evaluations = static_cast<int>(jobs.size());
  bool jac_ok = true;
  for (size_t i = 0; i < n; ++i) {
    if (plus[i].failed || minus[i].failed || hp[i] + hm[i] <= 0) {
      jac_ok = false;
      J.col(static_cast<Eigen::Index>(i)).setZero();
      continue;
    }
    J.col(static_cast<Eigen::Index>(i)) = (pr.residuals(plus[i]) - pr.residuals(minus[i])) / (hp[i] + hm[i]);
  }
  const double dof = std::max(1, r.residuals - static_cast<int>(n) - r.offset_parameters);
  const double s2 = std::isfinite(pr.w.noise) ? pr.w.noise * pr.w.noise : rf.squaredNorm() / dof;
  // (J^T J)^-1 in the parameters' scales, by eigen-decomposition: directions with an
  // eigenvalue below 1e-10 of the largest are not determined by the data.
  Eigen::MatrixXd D = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(n));
  for (size_t i = 0; i < n; ++i) D(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(i)) = pr.scale[i];
  const Eigen::MatrixXd Js = J * D;
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(Js.transpose() * Js);
  const VecX ev = es.eigenvalues();
  const double emax = ev.maxCoeff();
  Eigen::MatrixXd inv = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(n));
  std::vector<bool> undetermined(n, !jac_ok || !(emax > 0));
  for (Eigen::Index k = 0; k < ev.size(); ++k) {
    const VecX q = es.eigenvectors().col(k);
    if (ev[k] > 1e-10 * emax) {
      inv += q * q.transpose() / ev[k];
    } else {
      for (size_t i = 0; i < n; ++i)
        if (std::abs(q[static_cast<Eigen::Index>(i)]) > 1e-3) undetermined[i] = true;
    }
  }
  r.covariance = s2 * D * inv * D;
  // Roughness (see the header): the two halves of each central difference compared.
  for (size_t i = 0; i < n; ++i) {
    r.jacobian_steps.push_back(1e-2 * pr.scale[i]);
    double rho = std::numeric_limits<double>::quiet_NaN();
    if (!plus[i].failed && !minus[i].failed && hp[i] > 0 && hm[i] > 0) {
      rho = residualRoughness((pr.residuals(plus[i]) - rf) / hp[i], (rf - pr.residuals(minus[i])) / hm[i]);
    }
    r.roughness.push_back(rho);
  }
  for (size_t i = 0; i < n; ++i) {
    double se = undetermined[i] ? std::numeric_limits<double>::infinity()
                                : pr.scale[i] * std::sqrt(s2 * inv(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(i)));
    if (r.roughness[i] > kRoughness && se < r.jacobian_steps[i]) {
      const auto ii = static_cast<Eigen::Index>(i);
      r.covariance(ii, ii) += r.jacobian_steps[i] * r.jacobian_steps[i] - se * se;
      se = r.jacobian_steps[i];
    }
    r.std_errors.push_back(se);
    r.identifiable.push_back(std::isfinite(se) && se < std::abs(r.values[i]));
  }
  r.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (s.cancel && s.cancel->load()) throw CalibrationCancelled();  // (a Jacobian of stopped runs)
  return r;
}

}  // namespace needle_sim
