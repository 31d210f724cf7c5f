#pragma once
// A recorded insertion's axial holder force against time (doc/calibration.md): what a
// force/torque sensor on the needle holder measured, to compare the simulation with and to
// calibrate its parameters from. CSV with a header naming the columns `t` [s] and
// `axial_force` [N]: the needle's force on its holder along the needle, the sensor's reading
// as the simulation reports it (observables.hpp): negative when the tissue resists the
// insertion. Other columns are ignored.
#include <string>
#include <vector>

namespace needle_sim {

struct ForceRecord {
  std::vector<double> t, force;
};

// Rows a measurement stream may carry and an estimator must survive (assimilation): a
// non-finite value (a sensor dropout written as nan/inf) and a stale row (a time not after the
// last accepted one).
struct ForceCsvRejects {
  long nonfinite = 0, stale = 0;
};

// Throws InputError(file, column, problem) for a file that cannot be read, a missing column,
// a value that is not a number, fewer than 2 rows; and, unless `rejects` is given, for a
// non-finite value or times that do not increase strictly. With `rejects`, such rows are
// skipped and counted there instead.
ForceRecord readForceCsv(const std::string& path, ForceCsvRejects* rejects = nullptr);

// Linear interpolation of (t, y) at time x, clamped at the ends; t strictly increasing.
double interpolate(const std::vector<double>& t, const std::vector<double>& y, double x);

}  // namespace needle_sim
