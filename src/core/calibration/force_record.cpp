#include "needle_sim/calibration/force_record.hpp"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

namespace {
std::vector<std::string> splitCsv(const std::string& line) {
  std::vector<std::string> out;
  std::string cell;
  std::istringstream in(line);
  while (std::getline(in, cell, ',')) {
    cell.erase(0, cell.find_first_not_of(" \t\r"));
    cell.erase(cell.find_last_not_of(" \t\r") + 1);
    out.push_back(cell);
  }
  if (!line.empty() && line.back() == ',') out.emplace_back();
  return out;
}
}  // namespace

bool ForceRecord::hasForce() const {
  return std::any_of(force.begin(), force.end(), [](double f) { return std::isfinite(f); });
}

namespace {
bool anyFinite(const std::vector<Vec3>& v) {
  return std::any_of(v.begin(), v.end(), [](const Vec3& p) { return p.allFinite(); });
}
}  // namespace

bool ForceRecord::hasTip() const { return anyFinite(tip); }

bool ForceRecord::hasTarget(size_t j) const { return j < targets.size() && anyFinite(targets[j]); }

bool ForceRecord::hasShape() const {
  return std::any_of(shape.begin(), shape.end(), [](const std::vector<Vec3>& c) { return !c.empty(); });
}

size_t ForceRecord::shapePoints() const {
  size_t n = 0;
  for (const auto& c : shape) n = std::max(n, c.size());
  return n;
}

ForceRecord measurementRows(std::vector<MeasurementSample> samples, bool tip, int target, int num_targets, bool shape,
                            double shape_spacing) {
  std::stable_sort(samples.begin(), samples.end(), [](const MeasurementSample& a, const MeasurementSample& b) { return a.t < b.t; });
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  ForceRecord r;
  if (target >= 0) r.targets.assign(static_cast<size_t>(std::max(num_targets, target + 1)), {});
  r.shape_spacing = shape_spacing;
  for (const MeasurementSample& s : samples) {
    const bool taken = !r.t.empty() && std::abs(s.t - r.t.back()) < 1e-9 &&
                       (s.channel == 0   ? std::isfinite(r.force.back())
                        : s.channel == 1 ? r.tip.back().allFinite()
                        : s.channel == 3 ? !r.shape.back().empty()
                                         : r.targets[static_cast<size_t>(target)].back().allFinite());
    if (r.t.empty() || s.t > r.t.back() + 1e-9 || taken) {
      r.t.push_back(r.t.empty() ? s.t : std::max(s.t, r.t.back() + 1e-9));
      r.force.push_back(kNaN);
      if (tip) r.tip.push_back(Vec3::Constant(kNaN));
      if (target >= 0) r.targets[static_cast<size_t>(target)].push_back(Vec3::Constant(kNaN));
      if (shape) r.shape.emplace_back();
    }
    if (s.channel == 0) r.force.back() = s.force;
    else if (s.channel == 1) r.tip.back() = s.point;
    else if (s.channel == 3) r.shape.back() = s.shape;
    else r.targets[static_cast<size_t>(target)].back() = s.point;
  }
  return r;
}

CentreLineRequest CentreLineRequest::of(const ForceRecord& r) {
  CentreLineRequest q;
  q.points = r.shapePoints();
  q.spacing = r.shape_spacing;
  for (size_t i = 0; i < r.shape.size() && i < r.t.size(); ++i)
    if (!r.shape[i].empty()) q.times.push_back(r.t[i]);
  return q;
}

bool ForceRecord::hasTargets() const {
  for (size_t j = 0; j < targets.size(); ++j)
    if (hasTarget(j)) return true;
  return false;
}

ForceRecord readForceCsv(const std::string& path, ForceCsvRejects* rejects, const std::vector<std::string>& target_names) {
  std::ifstream f(path);
  if (!f) throw InputError(path, "", "cannot read the force record");
  std::string line;
  if (!std::getline(f, line)) throw InputError(path, "", "empty file: expected a header with t,axial_force");
  const auto header = splitCsv(line);
  constexpr size_t kNone = static_cast<size_t>(-1);
  const auto find = [&](const std::string& name) {
    const auto it = std::find(header.begin(), header.end(), name);
    return it == header.end() ? kNone : static_cast<size_t>(it - header.begin());
  };
  const size_t ct = find("t"), cf = find("axial_force");
  if (ct == kNone) throw InputError(path, "t", "missing column (the header has: " + line + ")");
  // A point channel's three columns, all or none.
  const auto triple = [&](const std::string& prefix, std::array<size_t, 3>& c) {
    for (int k = 0; k < 3; ++k) c[static_cast<size_t>(k)] = find(prefix + "xyz"[k]);
    const int n = (c[0] != kNone) + (c[1] != kNone) + (c[2] != kNone);
    if (n != 0 && n != 3)
      throw InputError(path, prefix + "x", "a point needs all three columns " + prefix + "x, " + prefix + "y, " + prefix +
                                               "z (the header has: " + line + ")");
    return n == 3;
  };
  std::array<size_t, 3> cp{};
  const bool tip = triple("tip_", cp);
  std::vector<std::array<size_t, 3>> ctarget(target_names.size());
  std::vector<bool> target(target_names.size());
  int channels = (cf != kNone) + (tip ? 1 : 0);
  for (size_t j = 0; j < target_names.size(); ++j) {
    target[j] = triple(target_names[j] + "_", ctarget[j]);
    channels += target[j] ? 1 : 0;
  }
  if (channels == 0)
    throw InputError(path, "axial_force", "missing column: a record needs axial_force, or tip_x, tip_y, tip_z" +
                                              std::string(target_names.empty() ? "" : ", or a target's <name>_x, _y, _z") +
                                              " (the header has: " + line + ")");
  ForceRecord r;
  long row = 1;
  while (std::getline(f, line)) {
    ++row;
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    const auto cells = splitCsv(line);
    long dropped = 0;  // this row's non-finite values (counted with rejects)
    // A channel's value: NaN for a blank cell (no sample) or, with rejects, a non-finite one.
    auto number = [&](size_t c, const std::string& name, bool optional) {
      if (c >= cells.size() || cells[c].empty()) {
        if (optional) return std::numeric_limits<double>::quiet_NaN();
        throw InputError(path, name, "row " + std::to_string(row) + " has no value");
      }
      const char* s = cells[c].c_str();
      char* end = nullptr;
      errno = 0;
      const double v = std::strtod(s, &end);
      const bool parsed = end != s && *end == '\0';
      if (parsed && rejects && !std::isfinite(v)) {
        ++dropped;
        return std::numeric_limits<double>::quiet_NaN();
      }
      if (!parsed || errno == ERANGE || !std::isfinite(v))
        throw InputError(path, name, "row " + std::to_string(row) + ": '" + cells[c] + "' is not a finite number");
      return v;
    };
    const bool both = channels > 1;  // a blank cell is a sensor without a sample then
    const double t = number(ct, "t", false);
    const double y = cf == kNone ? std::numeric_limits<double>::quiet_NaN() : number(cf, "axial_force", both);
    // A point's value: all three coordinates or none (NaN).
    const auto point = [&](const std::array<size_t, 3>& c, const std::string& prefix) {
      Vec3 p;
      for (int k = 0; k < 3; ++k) p[k] = number(c[static_cast<size_t>(k)], prefix + "xyz"[k], both);
      if (!p.allFinite()) p.setConstant(std::numeric_limits<double>::quiet_NaN());
      return p;
    };
    const Vec3 p = tip ? point(cp, "tip_") : Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
    std::vector<Vec3> q(target_names.size(), Vec3::Constant(std::numeric_limits<double>::quiet_NaN()));
    bool any_target = false;
    for (size_t j = 0; j < target_names.size(); ++j)
      if (target[j]) {
        q[j] = point(ctarget[j], target_names[j] + "_");
        any_target = any_target || q[j].allFinite();
      }
    if (std::isnan(t)) {  // with rejects, a non-finite time: the row is a dropout
      ++rejects->nonfinite;
      continue;
    }
    if (!std::isfinite(y) && !p.allFinite() && !any_target) {
      if (dropped == 0) throw InputError(path, "t", "row " + std::to_string(row) + " has no sample");
      ++rejects->nonfinite;
      continue;
    }
    if (dropped && rejects) ++rejects->nonfinite;  // one channel lost, the other kept
    if (!r.t.empty() && !(t > r.t.back())) {
      if (rejects) {
        ++rejects->stale;
        continue;
      }
      throw InputError(path, "t", "row " + std::to_string(row) + ": times must increase strictly (" +
                                      std::to_string(t) + " after " + std::to_string(r.t.back()) + ")");
    }
    r.t.push_back(t);
    r.force.push_back(y);
    if (tip) r.tip.push_back(p);
    r.targets.resize(target_names.size());
    for (size_t j = 0; j < target_names.size(); ++j)
      if (target[j]) r.targets[j].push_back(q[j]);
  }
  if (r.t.size() < 2) throw InputError(path, "t", "at least 2 rows are needed");
  return r;
}

double interpolate(const std::vector<double>& t, const std::vector<double>& y, double x) {
  if (x <= t.front()) return y.front();
  if (x >= t.back()) return y.back();
  const size_t i = static_cast<size_t>(std::upper_bound(t.begin(), t.end(), x) - t.begin());
  const double w = (x - t[i - 1]) / (t[i] - t[i - 1]);
  return (1 - w) * y[i - 1] + w * y[i];
}

PointSeries::PointSeries(const std::vector<Vec3>& p) {
  for (int k = 0; k < 3; ++k) {
    c_[k].reserve(p.size());
    for (const Vec3& x : p) c_[k].push_back(x[k]);
  }
}

Vec3 PointSeries::at(const std::vector<double>& t, double x) const {
  return Vec3(interpolate(t, c_[0], x), interpolate(t, c_[1], x), interpolate(t, c_[2], x));
}

}  // namespace needle_sim
