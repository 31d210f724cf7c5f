#include "needle_sim/calibration/force_assimilation.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"

namespace needle_sim {

namespace {
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kUntilEnd = 1e9;  // simulateHolderForce: the scene's whole duration

// The residuals' standard deviation, robustly: 1.4826 median |r| (a Gaussian's, unmoved by a
// few gross outliers).
double robustScale(const VecX& r) {
  std::vector<double> a(r.data(), r.data() + r.size());
  for (double& x : a) x = std::abs(x);
  if (a.empty()) return kInf;
  std::nth_element(a.begin(), a.begin() + a.size() / 2, a.end());
  return 1.4826 * a[a.size() / 2];
}
}  // namespace

ForceAssimilation::ForceAssimilation(AssimilationSettings s, ForceRecord data) : s_(std::move(s)), data_(std::move(data)) {
  if (!std::isnan(s_.fit.noise) && !(s_.fit.noise > 0 && std::isfinite(s_.fit.noise)))
    throw InputError("", "--noise", "the force measurement's noise (standard deviation, N) must be a positive number");
  if (!(s_.outlier_gate > 1)) throw InputError("", "outlier_gate", "must exceed 1 noise standard deviation");
  if (data_.t.size() < 2) throw InputError("", "--data", "at least 2 measured samples are needed");
  params_ = resolveParameters(s_.fit);
  every_ = s_.every > 0 ? s_.every : (data_.t.back() - data_.t.front()) / 10;
  if (!(every_ > 0)) throw InputError("", "--assimilate-every", "the data span no time");
  next_ = data_.t.front() + every_;
  for (size_t i = 0; i < data_.t.size(); ++i) samples_.push_back({data_.t[i], data_.force[i], 0.0, false, false});
  std::vector<double> v;
  for (const auto& p : params_) v.push_back(p.start);
  prediction_ = run(v, end());
  if (prediction_.failed) throw NumericalError(0, "the simulation fails at the nominal values: " + prediction_.failure);
}

double ForceAssimilation::end() const {
  // The scene's duration; a recorded session's commands last as long as the record (and its
  // last command).
  if (s_.fit.commands.empty()) return kUntilEnd;
  double e = data_.t.back();
  for (const auto& c : s_.fit.commands) e = std::max(e, c.received);
  return e;
}

std::vector<double> ForceAssimilation::values() const {
  if (!checkpoints_.empty()) return checkpoints_.back().values;
  std::vector<double> v;
  for (const auto& p : params_) v.push_back(p.start);
  return v;
}

SimulatedForce ForceAssimilation::run(const std::vector<double>& v, double until, bool target_errors) const {
  std::vector<std::string> sets = s_.fit.sets;
  for (const auto& o : parameterSets(params_, v)) sets.push_back(o);
  return simulateHolderForce(s_.fit.scene, sets, s_.fit.needle, until, &s_.fit.commands, target_errors);
}

int ForceAssimilation::advance(double t) {
  int made = 0;
  while (t + 1e-12 >= next_ && next_ <= data_.t.back() + 1e-12) {
    const size_t before = checkpoints_.size();
    checkpoint(next_);
    made += static_cast<int>(checkpoints_.size() - before);
    next_ += every_;
  }
  return made;
}

void ForceAssimilation::finish(double t) {
  // The samples up to the run's end (those after it never arrived).
  const double end = std::min(t, data_.t.back());
  if (fitted_until_ + 1e-12 < end) checkpoint(end);
  next_ = kInf;
}

void ForceAssimilation::checkpoint(double t) {
  const auto t0 = std::chrono::steady_clock::now();
  const size_t n = params_.size();
  // The samples that arrived since the last checkpoint, predicted before they are used.
  int fresh = 0;
  double innovation2 = 0;
  for (auto& x : samples_)
    if (x.t > fitted_until_ + 1e-12 && x.t <= t + 1e-12) {
      x.predicted = interpolate(prediction_.t, prediction_.force, x.t);
      x.arrived = true;
      innovation2 += (x.measured - x.predicted) * (x.measured - x.predicted);
      ++fresh;
    }
  auto window = [&] {
    ForceRecord w;
    for (const auto& x : samples_)
      if (x.t <= t + 1e-12 && !x.rejected) {
        w.t.push_back(x.t);
        w.force.push_back(x.measured);
      }
    return w;
  };
  ForceRecord w = window();
  if (w.t.size() < n + 2) return;  // not enough to fit yet: the samples wait for the next one

  CalibrationSettings c = s_.fit;
  c.parameters = params_;
  const std::vector<double> start = values();
  for (size_t i = 0; i < n; ++i) {
    c.parameters[i].start = std::clamp(start[i], params_[i].lower, params_[i].upper);
    c.parameters[i].scale = std::abs(params_[i].start) > 0 ? std::abs(params_[i].start) : 1.0;
    // Warm: where the last estimate determined the key (its standard deviation below a tenth
    // of its value) and fitted its data within their noise, the search starts within 3
    // standard deviations of it and stops when its steps fall below a twentieth of one (the
    // data since add less than that); otherwise from its default trust radius to xtol_rel (an
    // inconsistent fit may sit in a local minimum its small deviations would confine it to).
    if (!checkpoints_.empty() && checkpoints_.back().consistent) {
      const double sd = checkpoints_.back().stds[i];
      if (std::isfinite(sd) && sd < 0.1 * std::abs(checkpoints_.back().values[i])) {
        c.parameters[i].initial_step = 3 * sd;
        c.parameters[i].tolerance = 0.05 * sd;
      }
    }
  }
  CalibrationResult r = calibrate(c, w);
  int evaluations = r.evaluations + r.jacobian_evaluations + 1;
  // Outliers: residuals beyond the gate at the fit are rejected for good, and the window
  // refitted once (a gross outlier pulls the fit, never by as much as its own residual).
  // The gate in the larger of the stated noise and the residuals' robust scale: a noise stated
  // too small must not reject the measurement wholesale (the consistency flag says so instead).
  const double scale = robustScale(r.residuals_fit);
  const double gate = s_.outlier_gate * (stated() ? std::max(s_.fit.noise, scale) : scale);
  bool rejected = false;
  for (Eigen::Index j = 0; j < r.residuals_fit.size(); ++j)
    if (std::abs(r.residuals_fit[j]) > gate)
      for (auto& x : samples_)
        if (x.t == w.t[static_cast<size_t>(j)] && !x.rejected) {
          x.rejected = true;
          ++outliers_;
          rejected = true;
        }
  if (rejected) {
    w = window();
    if (w.t.size() < n + 2) return;
    r = calibrate(c, w);
    evaluations += r.evaluations + r.jacobian_evaluations + 1;
  }

  AssimilationCheckpoint k;
  k.t = t;
  k.samples = static_cast<int>(w.t.size());
  k.new_samples = fresh;
  k.values = r.values;
  k.stds = r.std_errors;
  k.rms = r.rms;
  k.innovation_rms = fresh ? std::sqrt(innovation2 / fresh) : 0.0;
  k.consistent = !stated() || k.samples < 10 || r.rms <= 1.5 * s_.fit.noise;
  if (!k.consistent) {
    // The residuals say the noise is larger than stated (or the model misses something): the
    // covariance takes their own scale, s^2 = RSS / (m - n), not the stated one (the Birge
    // ratio), so that the deviations reported are not the stated noise's.
    const double dof = std::max(1, k.samples - static_cast<int>(n));
    const double inflation = std::sqrt(r.residuals_fit.squaredNorm() / dof) / s_.fit.noise;
    if (inflation > 1) {
      for (double& sd : k.stds) sd *= inflation;
      r.covariance *= inflation * inflation;
    }
  }

  // The scene to its end with the estimate: the next samples' prediction and the targets'.
  prediction_ = run(k.values, end(), s_.target_errors && s_.predict_targets);
  ++evaluations;
  if (prediction_.failed) throw NumericalError(0, "the simulation fails at the estimate: " + prediction_.failure);
  const size_t nt = prediction_.target_end.size();
  k.target_end = prediction_.target_end;
  k.target_cov.assign(nt, Mat3::Zero());
  if (s_.predict_targets && nt > 0) {
    // G = d target_end / d key by forward differences (1 % of the value's scale; away from a
    // bound), G Cov G^T; a key the data do not determine makes the covariance infinite.
    bool determined = true;
    for (double sd : k.stds) determined = determined && std::isfinite(sd);
    if (!determined) {
      for (auto& m : k.target_cov) m = Mat3::Identity() * kInf;
    } else {
      std::vector<Eigen::Matrix<double, 3, Eigen::Dynamic>> G(nt, Eigen::Matrix<double, 3, Eigen::Dynamic>::Zero(3, n));
      for (size_t i = 0; i < n; ++i) {
        const double scale = std::abs(k.values[i]) > 0 ? std::abs(k.values[i]) : 1.0;
        double h = 1e-2 * scale;
        if (k.values[i] + h > params_[i].upper) h = -h;
        std::vector<double> v = k.values;
        v[i] += h;
        const SimulatedForce f = run(v, end());
        ++evaluations;
        if (f.failed || f.target_end.size() != nt) {
          for (auto& m : k.target_cov) m = Mat3::Identity() * kInf;
          determined = false;
          break;
        }
        for (size_t j = 0; j < nt; ++j) G[j].col(static_cast<Eigen::Index>(i)) = (f.target_end[j] - k.target_end[j]) / h;
      }
      if (determined)
        for (size_t j = 0; j < nt; ++j) k.target_cov[j] = G[j] * r.covariance * G[j].transpose();
    }
    if (s_.target_errors) {
      // The discretisation's part, independent of the parameters': a failed estimate (NaN)
      // leaves the covariance unknown (NaN), not smaller.
      k.target_bound = prediction_.target_end_bound;
      for (size_t j = 0; j < nt && j < k.target_bound.size(); ++j)
        k.target_cov[j] += k.target_bound[j].cwiseProduct(k.target_bound[j]).asDiagonal();
    }
  }
  k.evaluations = evaluations;
  k.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  checkpoints_.push_back(std::move(k));
  fitted_until_ = t;
}

}  // namespace needle_sim
