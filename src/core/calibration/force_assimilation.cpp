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

// A run's target j, mean over the times the window has its samples (NaN: none).
Vec3 sampledMean(const SimulatedForce& f, const ForceRecord& w, size_t j) {
  if (j >= f.targets.size() || j >= w.targets.size() || w.targets[j].empty()) return Vec3::Constant(NAN);
  const PointSeries c(f.targets[j]);
  Vec3 sum = Vec3::Zero();
  int n = 0;
  for (size_t i = 0; i < w.t.size(); ++i)
    if (w.targets[j][i].allFinite()) {
      sum += c.at(f.t, w.t[i]);
      ++n;
    }
  return n ? Vec3(sum / n) : Vec3::Constant(NAN);
}
}  // namespace

ForceAssimilation::ForceAssimilation(AssimilationSettings s, ForceRecord data) : s_(std::move(s)), data_(std::move(data)) {
  w_ = measurementWeights(s_.fit, data_);
  if (!(s_.outlier_gate > 1)) throw InputError("", "outlier_gate", "must exceed 1 noise standard deviation");
  if (data_.t.size() < 2) throw InputError("", "--data", "at least 2 measured samples are needed");
  params_ = resolveParameters(s_.fit);
  every_ = s_.every > 0 ? s_.every : (data_.t.back() - data_.t.front()) / 10;
  if (!(every_ > 0)) throw InputError("", "--assimilate-every", "the data span no time");
  next_ = data_.t.front() + every_;
  for (size_t i = 0; i < data_.t.size(); ++i) {
    AssimilationSample x;
    x.t = data_.t[i];
    x.measured = data_.force[i];
    if (!data_.tip.empty()) x.tip_measured = data_.tip[i];
    if (i < data_.shape.size()) x.shape_measured = data_.shape[i];
    for (const auto& q : data_.targets) {
      x.target_measured.push_back(q.empty() ? Vec3::Constant(NAN) : q[i]);
      x.target_predicted.push_back(Vec3::Zero());
      x.target_rejected.push_back(0);
    }
    samples_.push_back(x);
  }
  std::vector<double> v;
  for (const auto& p : params_) v.push_back(p.start);
  // The nominal run predicts the samples up to the first checkpoint: as far as the data go (a
  // node's first rows: not the whole scene, which the first estimate would wait for).
  predicted_until_ = std::min(end(), data_.t.back());
  prediction_ = run(v, predicted_until_, false, true);
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

SimulatedForce ForceAssimilation::run(const std::vector<double>& v, double until, bool target_errors, bool shape) const {
  std::vector<std::string> sets = s_.fit.sets;
  for (const auto& o : parameterSets(params_, v)) sets.push_back(o);
  CentreLineRequest c;
  if (shape) {
    c.points = data_.shapePoints();
    c.spacing = data_.shape_spacing;
  }
  return simulateHolderForce(s_.fit.scene, sets, s_.fit.needle, until, &s_.fit.commands, target_errors, s_.fit.limits,
                             s_.fit.cancel, c, s_.fit.target_edits);
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

void ForceAssimilation::append(const ForceRecord& rows) {
  for (size_t i = 0; i < rows.t.size(); ++i) {
    const double t = rows.t[i];
    if (!(t > data_.t.back())) throw InputError("", "t", "an appended sample is not after the data's last time");
    data_.t.push_back(t);
    data_.force.push_back(i < rows.force.size() ? rows.force[i] : NAN);
    AssimilationSample x;
    x.t = t;
    x.measured = data_.force.back();
    if (!data_.tip.empty()) {
      data_.tip.push_back(i < rows.tip.size() ? rows.tip[i] : Vec3::Constant(NAN));
      x.tip_measured = data_.tip.back();
    }
    if (!data_.shape.empty()) {
      data_.shape.push_back(i < rows.shape.size() ? rows.shape[i] : std::vector<Vec3>{});
      x.shape_measured = data_.shape.back();
    }
    for (size_t j = 0; j < data_.targets.size(); ++j) {
      Vec3 q = Vec3::Constant(NAN);
      if (!data_.targets[j].empty()) {
        if (j < rows.targets.size() && i < rows.targets[j].size()) q = rows.targets[j][i];
        data_.targets[j].push_back(q);
      }
      x.target_measured.push_back(q);
      x.target_predicted.push_back(Vec3::Zero());
      x.target_rejected.push_back(0);
    }
    samples_.push_back(x);
  }
  w_ = measurementWeights(s_.fit, data_);  // a channel may have its first sample now
}

void ForceAssimilation::setCommands(std::vector<RecordedCommand> commands) { s_.fit.commands = std::move(commands); }

void ForceAssimilation::setTargetEdits(std::vector<TargetEdit> edits) { s_.fit.target_edits = std::move(edits); }

void ForceAssimilation::update(double t) {
  const double until = std::min(t, data_.t.back());
  if (fitted_until_ + 1e-12 < until) checkpoint(until);
}

void ForceAssimilation::checkpoint(double t) {
  const auto t0 = std::chrono::steady_clock::now();
  const size_t n = params_.size();
  // Streaming: the last estimate's run stopped where the commands did then; the new samples
  // are predicted by it run over the commands as they are now.
  // A shape sample with more points than the prediction's centre line (the first ones
  // streamed) needs it again, too.
  size_t shape_points = 0;
  for (const auto& x : samples_)
    if (x.t > fitted_until_ + 1e-12 && x.t <= t + 1e-12) shape_points = std::max(shape_points, x.shape_measured.size());
  const size_t predicted_points = prediction_.shape.empty() ? 0 : prediction_.shape.front().size();
  if ((!s_.fit.commands.empty() && !prediction_.t.empty() && prediction_.t.back() + 1e-9 < t) ||
      predicted_until_ + 1e-9 < t || shape_points > predicted_points) {
    predicted_until_ = end();
    prediction_ = run(values(), predicted_until_, false, true);
    if (prediction_.failed) throw NumericalError(0, "the simulation fails at the estimate: " + prediction_.failure);
  }
  // The samples that arrived since the last checkpoint, predicted before they are used.
  int fresh = 0, fresh_values = 0;
  double innovation2 = 0;
  // Per sensor (force, tip, targets, shape): the sum of squared differences and the values.
  double sensor2[4] = {0, 0, 0, 0};
  int sensor_n[4] = {0, 0, 0, 0};
  const PointSeries tip(prediction_.tip);
  std::vector<PointSeries> target;
  for (const auto& q : prediction_.targets) target.emplace_back(q);
  for (auto& x : samples_)
    if (x.t > fitted_until_ + 1e-12 && x.t <= t + 1e-12) {
      x.arrived = true;
      ++fresh;
      if (x.hasForce()) {
        x.predicted = interpolate(prediction_.t, prediction_.force, x.t);
        innovation2 += (x.measured - x.predicted) * (x.measured - x.predicted);
        ++fresh_values;
        sensor2[0] += (x.measured - x.predicted) * (x.measured - x.predicted);
        ++sensor_n[0];
      }
      if (x.hasTip()) {
        x.tip_predicted = tip.at(prediction_.t, x.t);
        innovation2 += w_.tip_weight * w_.tip_weight * (x.tip_measured - x.tip_predicted).squaredNorm();
        fresh_values += 3;
        sensor2[1] += (x.tip_measured - x.tip_predicted).squaredNorm();
        sensor_n[1] += 3;
      }
      for (size_t j = 0; j < x.target_measured.size(); ++j)
        if (x.hasTarget(j) && j < target.size()) {
          // The model's, with the last estimate of the offset (none before the first).
          const Vec3 offset = j < offsets_.size() && offsets_[j].allFinite() ? offsets_[j] : Vec3::Zero();
          x.target_predicted[j] = target[j].at(prediction_.t, x.t) + offset;
          innovation2 += w_.target_weight * w_.target_weight * (x.target_measured[j] - x.target_predicted[j]).squaredNorm();
          fresh_values += 3;
          sensor2[2] += (x.target_measured[j] - x.target_predicted[j]).squaredNorm();
          sensor_n[2] += 3;
        }
      if (x.hasShape()) {
        x.shape_predicted = centreLineAt(prediction_, x.t);
        x.shape_predicted.resize(x.shape_measured.size(), Vec3::Constant(NAN));
        for (size_t q = 0; q < x.shape_measured.size(); ++q) {
          const double d2 = (x.shape_measured[q] - x.shape_predicted[q]).squaredNorm();
          innovation2 += w_.shape_weight * w_.shape_weight * d2;
          sensor2[3] += d2;
        }
        fresh_values += 3 * static_cast<int>(x.shape_measured.size());
        sensor_n[3] += 3 * static_cast<int>(x.shape_measured.size());
      }
    }
  // The window: the samples up to t, less the rejected channels; rows[i]: its sample.
  std::vector<size_t> rows;
  size_t values_in_window = 0;
  auto window = [&] {
    ForceRecord w;
    rows.clear();
    values_in_window = 0;
    const bool tip = !data_.tip.empty();
    w.targets.resize(data_.targets.size());
    w.shape_spacing = data_.shape_spacing;
    for (size_t i = 0; i < samples_.size(); ++i) {
      const auto& x = samples_[i];
      const bool f = x.hasForce() && !x.rejected, p = x.hasTip() && !x.tip_rejected;
      const bool c = x.hasShape() && !x.shape_rejected;
      int targets = 0;
      for (size_t j = 0; j < x.target_measured.size(); ++j) targets += x.hasTarget(j) && !x.target_rejected[j];
      if (x.t > t + 1e-12 || !(f || p || c || targets)) continue;
      w.t.push_back(x.t);
      w.force.push_back(f ? x.measured : NAN);
      if (tip) w.tip.push_back(p ? x.tip_measured : Vec3::Constant(NAN));
      if (!data_.shape.empty()) w.shape.push_back(c ? x.shape_measured : std::vector<Vec3>{});
      for (size_t j = 0; j < data_.targets.size(); ++j)
        if (!data_.targets[j].empty())
          w.targets[j].push_back(x.hasTarget(j) && !x.target_rejected[j] ? x.target_measured[j] : Vec3::Constant(NAN));
      rows.push_back(i);
      values_in_window += (f ? 1 : 0) + (p ? 3 : 0) + 3 * static_cast<size_t>(targets) + (c ? 3 * x.shape_measured.size() : 0);
    }
    return w;
  };
  ForceRecord w = window();
  if (values_in_window < n + 2) return;  // not enough to fit yet: the samples wait for the next one

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
  const double gate = s_.outlier_gate * (stated() ? std::max(w_.noise, scale) : scale);
  bool rejected = false;
  for (Eigen::Index j = 0; j < r.residuals_fit.size(); ++j)
    if (std::abs(r.residuals_fit[j]) > gate) {
      AssimilationSample& x = samples_[rows[static_cast<size_t>(r.residual_row[static_cast<size_t>(j)])]];
      const int channel = r.residual_channel[static_cast<size_t>(j)];
      const size_t target = channel >= 4 ? static_cast<size_t>((channel - 4) / 3) : 0;
      const bool already = channel < 0    ? x.shape_rejected
                           : channel == 0 ? x.rejected
                           : channel <= 3 ? x.tip_rejected
                                          : x.target_rejected[target] != 0;
      if (!already) {  // a point's sample once, whichever of its coordinates is off
        if (channel < 0) x.shape_rejected = true;
        else if (channel == 0) x.rejected = true;
        else if (channel <= 3) x.tip_rejected = true;
        else x.target_rejected[target] = 1;
        ++outliers_;
        rejected = true;
      }
    }
  if (rejected) {
    w = window();
    if (values_in_window < n + 2) return;
    r = calibrate(c, w);
    evaluations += r.evaluations + r.jacobian_evaluations + 1;
  }

  AssimilationCheckpoint k;
  k.t = t;
  k.samples = static_cast<int>(w.t.size());
  k.new_samples = fresh;
  k.values = r.values;
  k.stds = r.std_errors;
  k.roughness = r.roughness;
  k.rms = r.rms;
  k.innovation_rms = fresh_values ? std::sqrt(innovation2 / fresh_values) : 0.0;
  double* by_sensor[4] = {&k.innovation_force, &k.innovation_tip, &k.innovation_target, &k.innovation_shape};
  for (int c = 0; c < 4; ++c)
    if (sensor_n[c]) *by_sensor[c] = std::sqrt(sensor2[c] / sensor_n[c]);
  // Each sensor against its own noise too: a channel that misfits must not hide among the many
  // values of another (a shape's points outnumber the force's samples tenfold). The residuals
  // are weighted into the reference channel's units, so each channel's RMS is compared with
  // the reference noise. Per channel (force, tip, targets, shape) with 10 values or more.
  double channel2[4] = {0, 0, 0, 0};
  int channel_n[4] = {0, 0, 0, 0};
  for (Eigen::Index j = 0; j < r.residuals_fit.size(); ++j) {
    const int c = r.residual_channel[static_cast<size_t>(j)];
    const int g = c < 0 ? 3 : c == 0 ? 0 : c <= 3 ? 1 : 2;
    channel2[g] += r.residuals_fit[j] * r.residuals_fit[j];
    ++channel_n[g];
  }
  double worst = 0;  // the largest channel's RMS
  for (int g = 0; g < 4; ++g)
    if (channel_n[g] >= 10) worst = std::max(worst, std::sqrt(channel2[g] / channel_n[g]));
  k.consistent = !stated() || k.samples < 10 || (r.rms <= 1.5 * w_.noise && worst <= 1.5 * w_.noise);
  // The residuals' own scale, s^2 = RSS / (m - n - offsets); inconsistent, the worst channel's
  // if that is larger.
  const double own = std::sqrt(r.residuals_fit.squaredNorm() / std::max(1, r.residuals - static_cast<int>(n) - r.offset_parameters));
  double s_eff = stated() ? w_.noise : own;  // the noise the covariance is scaled by
  if (!k.consistent) {
    // The residuals say the noise is larger than stated (or the model misses something): the
    // covariance takes their own scale, not the stated one (the Birge ratio), so that the
    // deviations reported are not the stated noise's.
    const double inflation = std::max(own, worst) / w_.noise;
    if (inflation > 1) {
      for (double& sd : k.stds) sd *= inflation;
      r.covariance *= inflation * inflation;
      s_eff = std::max(own, worst);
    }
  }
  k.target_offset = r.target_offsets;
  offsets_ = r.target_offsets;
  // The parameters are known: a consumer may take them now, before the targets' prediction
  // (whole-scene runs, most of a checkpoint's time when the window is short).
  if (s_.on_fit) s_.on_fit(k);

  // The scene to its end with the estimate: the next samples' prediction and the targets'.
  predicted_until_ = end();
  prediction_ = run(k.values, predicted_until_, s_.target_errors && s_.predict_targets, true);
  ++evaluations;
  if (prediction_.failed) throw NumericalError(0, "the simulation fails at the estimate: " + prediction_.failure);
  const size_t nt = prediction_.target_end.size();
  // A measured target: the model's end less its mean at the sampled times (what the offset
  // pins to the measurements); else its end.
  const auto anchored = [&](const SimulatedForce& f, size_t j) {
    const bool measured = j < k.target_offset.size() && k.target_offset[j].allFinite();
    return measured ? Vec3(f.target_end[j] - sampledMean(f, w, j)) : f.target_end[j];
  };
  k.target_end = prediction_.target_end;
  for (size_t j = 0; j < nt && j < k.target_offset.size(); ++j)
    if (k.target_offset[j].allFinite()) k.target_end[j] += k.target_offset[j];
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
        for (size_t j = 0; j < nt; ++j) G[j].col(static_cast<Eigen::Index>(i)) = (anchored(f, j) - anchored(prediction_, j)) / h;
      }
      if (determined)
        for (size_t j = 0; j < nt; ++j) k.target_cov[j] = G[j] * r.covariance * G[j].transpose();
    }
    // A measured target's offset: the mean of its samples' noise, s^2 / samples per axis.
    for (size_t j = 0; j < nt && j < k.target_offset.size(); ++j)
      if (k.target_offset[j].allFinite()) {
        int samples = 0;
        for (const Vec3& q : w.targets[j]) samples += q.allFinite() ? 1 : 0;
        const double sd = s_eff / w_.target_weight;
        k.target_cov[j] += Mat3::Identity() * (sd * sd / std::max(1, samples));
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
