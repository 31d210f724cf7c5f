#include "assimilate.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>

#include "calibrate.hpp"
#include "needle_sim/core/error.hpp"

using namespace needle_sim;

namespace {
ForceCsvRejects g_rejects;  // the data file's skipped rows (one run per process)

nlohmann::json finiteOrNull(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); }
}  // namespace

std::unique_ptr<ForceAssimilation> makeAssimilation(const AssimilateOptions& o, const std::string& scene,
                                                    const std::vector<std::string>& sets, int needle,
                                                    const ForceRecord* bag_force,
                                                    const std::vector<RecordedCommand>* commands,
                                                    const std::vector<std::string>& target_names) {
  AssimilationSettings s;
  s.fit.scene = scene;
  s.fit.sets = sets;
  s.fit.needle = needle;
  s.fit.noise = o.noise;
  s.fit.tip_noise = o.tip_noise;
  s.fit.target_noise = o.target_noise;
  s.fit.shape_noise = o.shape_noise;
  s.every = o.every;
  s.target_errors = o.target_error;
  if (commands) s.fit.commands = *commands;
  s.fit.parameters = parseFitKeys(o.keys, o.starts, o.bounds);
  ForceRecord data;
  if (!o.data.empty()) {
    data = readForceCsv(o.data, &g_rejects, target_names);
  } else if (bag_force && !bag_force->t.empty()) {
    data = *bag_force;
  } else {
    throw InputError("", "--data", "--assimilate needs the measurement: --data FILE.csv, or --bag with a measurement topic "
                                     "(--wrench-topic, --tip-topic, --target-topic, --shape-topic)");
  }
  return std::make_unique<ForceAssimilation>(std::move(s), std::move(data));
}

void writeAssimilation(const ForceAssimilation& a, const AssimilateOptions& o, const std::string& out_dir,
                       const std::vector<std::string>& target_names) {
  const auto& p = a.parameters();
  const auto& cps = a.checkpoints();
  // Targets whose positions the record measures.
  const auto measured = [&](size_t j) {
    for (const auto& x : a.samples())
      if (x.hasTarget(j)) return true;
    return false;
  };
  {
    std::ofstream f(out_dir + "/assimilation.csv");
    if (!f) throw std::runtime_error("cannot write " + out_dir + "/assimilation.csv");
    f.precision(10);
    f << "t,samples,new_samples";
    for (const auto& q : p) f << ',' << q.key << ',' << q.key << "_std";
    for (const auto& q : p) f << ',' << q.key << "_roughness";
    f << ",rms_residual,innovation_rms,consistent";
    for (const auto& n : target_names)
      for (const char* c : {"x", "y", "z"}) f << ',' << n << "_end_" << c;
    for (const auto& n : target_names)
      for (const char* c : {"x", "y", "z"}) f << ',' << n << "_end_std_" << c;
    if (o.target_error)
      for (const auto& n : target_names)
        for (const char* c : {"x", "y", "z"}) f << ',' << n << "_end_bound_" << c;
    for (size_t j = 0; j < target_names.size(); ++j)
      if (measured(j))
        for (const char* c : {"x", "y", "z"}) f << ',' << target_names[j] << "_offset_" << c;
    f << ",evaluations,wall_s\n";
    for (const auto& k : cps) {
      f << k.t << ',' << k.samples << ',' << k.new_samples;
      for (size_t i = 0; i < p.size(); ++i) f << ',' << k.values[i] << ',' << k.stds[i];
      for (size_t i = 0; i < p.size(); ++i) f << ',' << (i < k.roughness.size() ? k.roughness[i] : NAN);
      f << ',' << k.rms << ',' << k.innovation_rms << ',' << (k.consistent ? 1 : 0);
      for (const auto& x : k.target_end) f << ',' << x[0] << ',' << x[1] << ',' << x[2];
      for (const auto& c : k.target_cov) f << ',' << std::sqrt(c(0, 0)) << ',' << std::sqrt(c(1, 1)) << ',' << std::sqrt(c(2, 2));
      if (o.target_error)
        for (size_t j = 0; j < target_names.size(); ++j) {
          const Vec3 b = j < k.target_bound.size() ? k.target_bound[j] : Vec3::Constant(NAN);
          f << ',' << b[0] << ',' << b[1] << ',' << b[2];
        }
      for (size_t j = 0; j < target_names.size(); ++j)
        if (measured(j)) {
          const Vec3 q = j < k.target_offset.size() ? k.target_offset[j] : Vec3::Constant(NAN);
          f << ',' << q[0] << ',' << q[1] << ',' << q[2];
        }
      f << ',' << k.evaluations << ',' << k.wall_s << '\n';
    }
  }
  {
    std::ofstream f(out_dir + "/innovation.csv");
    if (!f) throw std::runtime_error("cannot write " + out_dir + "/innovation.csv");
    f.precision(10);
    f << "t,measured,predicted,innovation,rejected\n";
    for (const auto& x : a.samples())
      if (x.arrived && x.hasForce())  // the samples after the run's end were never predicted nor used
        f << x.t << ',' << x.measured << ',' << x.predicted << ',' << x.measured - x.predicted << ',' << (x.rejected ? 1 : 0)
        << '\n';
  }
  bool tip = false, any_target = false, shape = false;
  for (const auto& x : a.samples()) tip = tip || x.hasTip(), shape = shape || x.hasShape();
  for (size_t j = 0; j < target_names.size(); ++j) any_target = any_target || measured(j);
  if (any_target) {
    // The measured targets' innovations [m], the scene's frame: a row per target sample.
    std::ofstream f(out_dir + "/innovation_targets.csv");
    if (!f) throw std::runtime_error("cannot write " + out_dir + "/innovation_targets.csv");
    f.precision(10);
    f << "t,target,measured_x,measured_y,measured_z,predicted_x,predicted_y,predicted_z,innovation_x,innovation_y,innovation_z,"
         "rejected\n";
    for (const auto& x : a.samples())
      for (size_t j = 0; j < target_names.size(); ++j)
        if (x.arrived && x.hasTarget(j)) {
          const Vec3 d = x.target_measured[j] - x.target_predicted[j];
          f << x.t << ',' << target_names[j];
          for (const Vec3* v : {&x.target_measured[j], &x.target_predicted[j], &d}) f << ',' << (*v)[0] << ',' << (*v)[1] << ',' << (*v)[2];
          f << ',' << (x.target_rejected[j] ? 1 : 0) << '\n';
        }
  }
  if (tip) {
    // The tracker's innovations [m], the scene's frame.
    std::ofstream f(out_dir + "/innovation_tip.csv");
    if (!f) throw std::runtime_error("cannot write " + out_dir + "/innovation_tip.csv");
    f.precision(10);
    f << "t,measured_x,measured_y,measured_z,predicted_x,predicted_y,predicted_z,innovation_x,innovation_y,innovation_z,rejected\n";
    for (const auto& x : a.samples())
      if (x.arrived && x.hasTip()) {
        const Vec3 d = x.tip_measured - x.tip_predicted;
        f << x.t;
        for (const Vec3* v : {&x.tip_measured, &x.tip_predicted, &d}) f << ',' << (*v)[0] << ',' << (*v)[1] << ',' << (*v)[2];
        f << ',' << (x.tip_rejected ? 1 : 0) << '\n';
      }
  }
  if (shape) {
    // A shape sensor's innovations [m]: per sample, the RMS over its points and coordinates,
    // and the largest point's distance.
    std::ofstream f(out_dir + "/innovation_shape.csv");
    if (!f) throw std::runtime_error("cannot write " + out_dir + "/innovation_shape.csv");
    f.precision(10);
    f << "t,points,innovation_rms,innovation_max,rejected\n";
    for (const auto& x : a.samples())
      if (x.arrived && x.hasShape()) {
        double sum = 0, largest = 0;
        for (size_t q = 0; q < x.shape_measured.size() && q < x.shape_predicted.size(); ++q) {
          const double d = (x.shape_measured[q] - x.shape_predicted[q]).norm();
          sum += d * d;
          largest = std::max(largest, d);
        }
        f << x.t << ',' << x.shape_measured.size() << ',' << std::sqrt(sum / (3.0 * x.shape_measured.size())) << ','
          << largest << ',' << (x.shape_rejected ? 1 : 0) << '\n';
      }
  }
  nlohmann::json params = nlohmann::json::object();
  const std::vector<double> v = a.values();
  for (size_t i = 0; i < p.size(); ++i)
    params[p[i].key] = {{"value", v[i]},
                        {"std", cps.empty() ? nlohmann::json(nullptr) : finiteOrNull(cps.back().stds[i])},
                        {"roughness", cps.empty() || i >= cps.back().roughness.size() ? nlohmann::json(nullptr)
                                                                                       : finiteOrNull(cps.back().roughness[i])},
                        {"start", p[i].start},
                        {"lower", p[i].lower},
                        {"upper", p[i].upper}};
  nlohmann::json targets = nlohmann::json::object();
  if (!cps.empty())
    for (size_t j = 0; j < target_names.size() && j < cps.back().target_end.size(); ++j) {
      const Vec3& x = cps.back().target_end[j];
      const Mat3& c = cps.back().target_cov[j];
      nlohmann::json cov = nlohmann::json::array();
      for (int r = 0; r < 3; ++r)
        for (int q = 0; q < 3; ++q) cov.push_back(finiteOrNull(c(r, q)));
      targets[target_names[j]] = {{"end_position", {x[0], x[1], x[2]}}, {"end_covariance", cov}};
      if (j < cps.back().target_offset.size() && measured(j)) {
        const Vec3& q = cps.back().target_offset[j];
        targets[target_names[j]]["offset"] = {finiteOrNull(q[0]), finiteOrNull(q[1]), finiteOrNull(q[2])};
      }
      if (o.target_error && j < cps.back().target_bound.size()) {
        const Vec3& b = cps.back().target_bound[j];
        targets[target_names[j]]["end_discretisation_bound"] = {finiteOrNull(b[0]), finiteOrNull(b[1]), finiteOrNull(b[2])};
      }
    }
  nlohmann::json channels = nlohmann::json::array();
  bool force = false;
  for (const auto& x : a.samples()) force = force || x.hasForce();
  if (force) channels.push_back("axial_force");
  if (tip) channels.push_back("tip");
  for (size_t j = 0; j < target_names.size(); ++j)
    if (measured(j)) channels.push_back(target_names[j]);
  if (shape) channels.push_back("shape");
  int inconsistent = 0;
  for (const auto& k : cps) inconsistent += k.consistent ? 0 : 1;
  const nlohmann::json section = {
      {"data", o.data},
      {"noise", finiteOrNull(o.noise)},
      {"tip_noise", finiteOrNull(o.tip_noise)},
      {"target_noise", finiteOrNull(o.target_noise)},
      {"shape_noise", finiteOrNull(o.shape_noise)},
      {"channels", channels},
      {"residual_units", a.weights().units},
      {"every_s", a.every()},
      {"checkpoints", cps.size()},
      {"parameters", params},
      {"targets", targets},
      {"samples", a.samples().size()},
      {"rejected", {{"nonfinite", g_rejects.nonfinite}, {"stale", g_rejects.stale}, {"outliers", a.outliers()}}},
      {"rms_residual", cps.empty() ? nlohmann::json(nullptr) : nlohmann::json(cps.back().rms)},
      {"consistent", cps.empty() || cps.back().consistent},
      {"inconsistent_checkpoints", inconsistent}};
  const std::string path = out_dir + "/summary.json";
  nlohmann::json j;
  {
    std::ifstream in(path);
    if (in) in >> j;
  }
  j["assimilation"] = section;
  std::ofstream(path) << j.dump(2) << '\n';

  std::printf("needle_sim: assimilation of %s: %zu checkpoints, %zu samples (%ld non-finite and %ld stale rows skipped, "
              "%ld outliers rejected)\n",
              o.data.empty() ? "the bag's wrench" : o.data.c_str(), cps.size(), a.samples().size(), g_rejects.nonfinite,
              g_rejects.stale, a.outliers());
  for (size_t i = 0; i < p.size(); ++i) {
    const double sd = cps.empty() ? NAN : cps.back().stds[i];
    std::printf("  %-32s %.6g +- %.3g (nominal %.6g)\n", p[i].key.c_str(), v[i], sd, p[i].start);
  }
  if (!cps.empty() && !cps.back().consistent)
    std::fprintf(stderr, "needle_sim: WARNING: the fit's residuals (RMS %.3g %s) exceed the stated noise %.3g %s by more "
                         "than 1.5x: the model does not fit the measurement; do not trust the estimate\n",
                 cps.back().rms, a.weights().units, a.weights().noise, a.weights().units);
}
