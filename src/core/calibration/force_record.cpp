#include "needle_sim/calibration/force_record.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <fstream>
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

ForceRecord readForceCsv(const std::string& path, ForceCsvRejects* rejects) {
  std::ifstream f(path);
  if (!f) throw InputError(path, "", "cannot read the force record");
  std::string line;
  if (!std::getline(f, line)) throw InputError(path, "", "empty file: expected a header with t,axial_force");
  const auto header = splitCsv(line);
  const auto col = [&](const std::string& name) {
    const auto it = std::find(header.begin(), header.end(), name);
    if (it == header.end()) throw InputError(path, name, "missing column (the header has: " + line + ")");
    return static_cast<size_t>(it - header.begin());
  };
  const size_t ct = col("t"), cf = col("axial_force");
  ForceRecord r;
  long row = 1;
  while (std::getline(f, line)) {
    ++row;
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    const auto cells = splitCsv(line);
    bool finite = true;
    auto number = [&](size_t c, const std::string& name) {
      if (c >= cells.size()) throw InputError(path, name, "row " + std::to_string(row) + " has no value");
      const char* s = cells[c].c_str();
      char* end = nullptr;
      errno = 0;
      const double v = std::strtod(s, &end);
      const bool parsed = end != s && *end == '\0';
      if (parsed && rejects && !std::isfinite(v)) finite = false;
      else if (!parsed || errno == ERANGE || !std::isfinite(v))
        throw InputError(path, name, "row " + std::to_string(row) + ": '" + cells[c] + "' is not a finite number");
      return v;
    };
    const double t = number(ct, "t"), y = number(cf, "axial_force");
    if (!finite) {
      ++rejects->nonfinite;
      continue;
    }
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

}  // namespace needle_sim
