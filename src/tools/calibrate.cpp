#include "calibrate.hpp"

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "bag_input.hpp"
#include "needle_sim/calibration/force_calibration.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "share_dir.hpp"

using namespace needle_sim;

namespace {

double number(const std::string& text, const std::string& option) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (text.empty() || *end || !std::isfinite(v)) throw InputError("", option, "'" + text + "' is not a finite number");
  return v;
}

// "key=value" -> (key, value)
std::pair<std::string, std::string> keyValue(const std::string& s, const std::string& option) {
  const size_t eq = s.find('=');
  if (eq == std::string::npos || eq == 0) throw InputError("", option, "expected key=value, got '" + s + "'");
  return {s.substr(0, eq), s.substr(eq + 1)};
}

CalibrationParameter& find(std::vector<CalibrationParameter>& p, const std::string& key, const std::string& option) {
  for (auto& q : p)
    if (q.key == key) return q;
  throw InputError("", option, "'" + key + "' is not among the keys to fit");
}

// The plotting script beside the executable (devel or install space) or in the share dir.
std::string plotScript() {
  std::error_code ec;
  const auto exe = std::filesystem::read_symlink("/proc/self/exe", ec);
  for (const auto& c : {exe.parent_path() / "plot_calibration.py",
                        std::filesystem::path(shareDir()) / "scripts" / "plot_calibration.py"})
    if (std::filesystem::exists(c, ec)) return c.string();
  return "";
}

}  // namespace

std::vector<CalibrationParameter> parseFitKeys(const std::vector<std::string>& lists, const std::vector<std::string>& starts,
                                               const std::vector<std::string>& bounds) {
  std::vector<CalibrationParameter> out;
  for (const auto& list : lists) {
    std::stringstream in(list);
    std::string key;
    while (std::getline(in, key, ','))
      if (!key.empty()) out.push_back(CalibrationParameter{key});
  }
  for (const auto& st : starts) {
    const auto [k, v] = keyValue(st, "--start");
    find(out, k, "--start").start = number(v, "--start");
  }
  for (const auto& b : bounds) {
    const auto [k, v] = keyValue(b, "--bounds");
    const size_t colon = v.find(':');
    if (colon == std::string::npos) throw InputError("", "--bounds", "expected key=lower:upper, got '" + b + "'");
    auto& p = find(out, k, "--bounds");
    p.lower = number(v.substr(0, colon), "--bounds");
    p.upper = number(v.substr(colon + 1), "--bounds");
  }
  return out;
}

int calibrateCommand(const CalibrateOptions& o) {
  const bool bag = o.data.size() > 4 && o.data.substr(o.data.size() - 4) == ".bag";
  if (bag && (o.pose_topic.empty() || o.wrench_topic.empty()))
    throw InputError(o.data, o.pose_topic.empty() ? "--pose-topic" : "--wrench-topic",
                     "a bag needs --pose-topic (the commanded base poses) and --wrench-topic (the measured wrench)");
  if (!bag && (!o.pose_topic.empty() || !o.wrench_topic.empty()))
    throw InputError(o.data, "--pose-topic", "topics are for a bag (.bag) record; a CSV has the columns t,axial_force");
  CalibrationSettings s;
  s.scene = o.scene;
  s.sets = o.sets;
  s.max_evaluations = o.max_evaluations;
  s.xtol_rel = o.xtol_rel;
  s.parameters = parseFitKeys(o.fit, o.starts, o.bounds);
  const Scene scene = loadScene(o.scene, o.sets);
  if (!o.needle.empty()) {
    s.needle = -1;
    for (size_t i = 0; i < scene.needles.size(); ++i)
      if (scene.needles[i].name == o.needle) s.needle = static_cast<int>(i);
    if (s.needle < 0) throw InputError(o.scene, "--needle", "no needle named '" + o.needle + "'");
  } else if (scene.needles.empty()) {
    throw InputError(o.scene, "needle", "the scene has no needle whose force could be fitted");
  }
  ForceRecord data;
  if (bag) {
    BagTopics topics;
    topics.pose = o.pose_topic;
    topics.wrench = o.wrench_topic;
    BagSession session = readBagSession(o.data, topics, s.needle, scene.needles[s.needle].length);
    data = std::move(session.force);
    s.commands = std::move(session.commands);
  } else {
    data = readForceCsv(o.data);
    // calibrate fits the force and reports it (fit.csv, fit.png); a tracked tip is
    // assimilated by `run --assimilate` with its noise.
    data.tip.clear();
    if (!data.hasForce()) throw InputError(o.data, "axial_force", "calibrate fits the holder force: the record has no axial_force (a tracked tip is for run --assimilate with --tip-noise)");
  }
  std::filesystem::create_directories(o.out);

  if (!o.quiet) std::fprintf(stderr, "needle_sim calibrate: %zu parameters, %zu samples\n", s.parameters.size(), data.t.size());
  const CalibrationResult r = calibrate(s, data, [&](int k, double rms, const std::vector<double>& v) {
    if (o.quiet) return;
    std::fprintf(stderr, "  evaluation %3d  rms %.4e N ", k, rms);
    for (double x : v) std::fprintf(stderr, " %.6g", x);
    std::fprintf(stderr, "\n");
  });
  const std::vector<std::string> sets = parameterSets(r.parameters, r.values);

  nlohmann::json params = nlohmann::json::object();
  for (size_t i = 0; i < r.parameters.size(); ++i) {
    const auto& p = r.parameters[i];
    params[p.key] = {{"value", r.values[i]},
                     {"std_error", std::isfinite(r.std_errors[i]) ? nlohmann::json(r.std_errors[i]) : nlohmann::json(nullptr)},
                     {"identifiable", static_cast<bool>(r.identifiable[i])},
                     {"roughness", std::isfinite(r.roughness[i]) ? nlohmann::json(r.roughness[i]) : nlohmann::json(nullptr)},
                     {"start", p.start},
                     {"lower", p.lower},
                     {"upper", p.upper}};
  }
  std::string set_line;
  for (const auto& x : sets) set_line += (set_line.empty() ? "" : " ") + std::string("--set ") + x;
  nlohmann::json j = {{"scene", o.scene},
                      {"data", o.data},
                      {"fixed_sets", o.sets},
                      {"parameters", params},
                      {"rms_residual_n", r.rms},
                      {"rms_residual_start_n", r.rms_start},
                      {"samples", r.residuals},
                      {"evaluations", r.evaluations},
                      {"failed_evaluations", r.failed_evaluations},
                      {"jacobian_evaluations", r.jacobian_evaluations},
                      {"wall_s", r.wall_s},
                      {"stop_reason", r.stop_reason},
                      {"set", set_line}};
  {
    std::ofstream f(o.out + "/calibration.json");
    if (!f) throw std::runtime_error("cannot write " + o.out + "/calibration.json");
    f << j.dump(2) << '\n';
  }
  {
    std::ofstream f(o.out + "/fit.csv");
    if (!f) throw std::runtime_error("cannot write " + o.out + "/fit.csv");
    f << "t,advance,measured,start,fitted\n";
    f.precision(10);
    const double until = r.fitted_run.t.empty() ? 0 : r.fitted_run.t.back();
    for (size_t i = 0; i < data.t.size(); ++i) {
      if (data.t[i] > until + 1e-12) break;
      f << data.t[i] << ',' << interpolate(r.fitted_run.t, r.fitted_run.advance, data.t[i]) << ',' << data.force[i] << ','
        << interpolate(r.start_run.t, r.start_run.force, data.t[i]) << ','
        << interpolate(r.fitted_run.t, r.fitted_run.force, data.t[i]) << '\n';
    }
  }
  std::printf("needle_sim calibrate: rms residual %.4e N (start %.4e N), %d evaluations (%d failed) + %d for the "
              "Jacobian, %.1f s, %s\n",
              r.rms, r.rms_start, r.evaluations, r.failed_evaluations, r.jacobian_evaluations, r.wall_s,
              r.stop_reason.c_str());
  for (size_t i = 0; i < r.parameters.size(); ++i)
    std::printf("  %-32s %.6g +- %s%s\n", r.parameters[i].key.c_str(), r.values[i],
                std::isfinite(r.std_errors[i]) ? (std::to_string(r.std_errors[i])).c_str() : "inf",
                r.identifiable[i] ? "" : "   NOT IDENTIFIED by these data (standard error larger than the value)");
  std::printf("reproduce: %s\n", set_line.c_str());
  if (o.plot) {
    const std::string script = plotScript();
    if (script.empty()) {
      std::fprintf(stderr, "needle_sim calibrate: plot_calibration.py not found; no fit.png\n");
    } else {
      const std::string cmd = "/usr/bin/python3 '" + script + "' '" + o.out + "'";
      if (std::system(cmd.c_str()) != 0) std::fprintf(stderr, "needle_sim calibrate: %s failed; no fit.png\n", cmd.c_str());
    }
  }
  return 0;
}
