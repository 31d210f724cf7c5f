#pragma once
// A recorded insertion's axial holder force against time (doc/calibration.md): what a
// force/torque sensor on the needle holder measured, to compare the simulation with and to
// calibrate its parameters from. CSV with a header naming the columns `t` [s] and
// `axial_force` [N]: the needle's force on its holder along the needle, the sensor's reading
// as the simulation reports it (observables.hpp): negative when the tissue resists the
// insertion. Optionally (or instead of the force) a tracker's tip position, `tip_x`, `tip_y`,
// `tip_z` [m, the scene's frame]: the needle's tip as the run's `<needle>_tip_*` columns give
// it. And, for a target the caller names (e.g. from an intraoperative image), its measured
// position `<target>_x`, `_y`, `_z` [m, the scene's frame: the run's target columns]. Sensors
// at different rates leave a blank cell where they have no sample. Other columns are ignored.
// A shape sensor's centre line (a fibre-Bragg grating along the needle) comes from the node's
// ~<needle>/measured_shape only (ForceRecord::shape), not from the CSV.
#include <array>
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct ForceRecord {
  std::vector<double> t, force;  // force NaN: no force sample in that row
  std::vector<Vec3> tip;         // empty: no tip channel; else per row, NaN: no tip sample
  // Per target named to the reader: empty (no columns), else per row (NaN: no sample).
  std::vector<std::vector<Vec3>> targets;
  // A shape sensor's samples: empty (no channel), else per row the needle's centre line at arc
  // lengths 0, shape_spacing, 2 shape_spacing, ... back from its tip [m, the scene's frame]
  // (empty: no sample in that row).
  std::vector<std::vector<Vec3>> shape;
  double shape_spacing = 0;
  bool hasForce() const;         // a finite force in some row
  bool hasTip() const;
  bool hasTarget(size_t j) const;
  bool hasTargets() const;
  bool hasShape() const;
  size_t shapePoints() const;  // the most points in a row
};

// One sensor's sample, before it is laid into a record's rows (the node's measurement topics,
// a bag's): channel 0 the force, 1 the tip, 2 the measured target, 3 the shape.
struct MeasurementSample {
  double t = 0;
  int channel = 0;
  double force = 0;
  Vec3 point = Vec3::Zero();
  std::vector<Vec3> shape;  // from the tip back (ForceRecord::shape)
};

// The samples (any order) laid into a record's rows, in time: samples of different sensors
// at one time share a row; a second sample of one sensor at that time starts a row of its own
// a nanosecond later (the record's times increase strictly). The record has the force channel
// and, as asked, the tip, target `target` of `num_targets` (< 0: none) and the shape.
ForceRecord measurementRows(std::vector<MeasurementSample> samples, bool tip, int target, int num_targets, bool shape,
                            double shape_spacing);

// A run's needle centre line at a measured shape's points (ForceRecord::shape): the arc
// lengths back from the tip, at the steps around the given times (one step either side: linear
// interpolation between them is the same as between all steps); no times: every step.
struct CentreLineRequest {
  double spacing = 0;
  size_t points = 0;
  std::vector<double> times;
  static CentreLineRequest of(const ForceRecord& r);  // at the record's shape samples
  bool wanted() const { return points > 0; }
};

// Rows a measurement stream may carry and an estimator must survive (assimilation): a
// non-finite value (a sensor dropout written as nan/inf) and a stale row (a time not after the
// last accepted one).
struct ForceCsvRejects {
  long nonfinite = 0, stale = 0;
};

// Throws InputError(file, column, problem) for a file that cannot be read, no `t` column or
// no channel (axial_force; tip_x, tip_y, tip_z; a target's three), a value that is not a number,
// a row with no sample, fewer than 2 rows; and, unless `rejects` is given, for a non-finite
// value or times that do not increase strictly. With `rejects`, such values (a row's channel)
// and rows are skipped and counted there instead.
ForceRecord readForceCsv(const std::string& path, ForceCsvRejects* rejects = nullptr,
                         const std::vector<std::string>& target_names = {});

// Linear interpolation of (t, y) at time x, clamped at the ends; t strictly increasing.
double interpolate(const std::vector<double>& t, const std::vector<double>& y, double x);

// A simulated point's per-step positions (the tip, a target), split into its coordinates
// once, interpolated at measured times as interpolate() does each.
class PointSeries {
 public:
  explicit PointSeries(const std::vector<Vec3>& p);
  Vec3 at(const std::vector<double>& t, double x) const;

 private:
  std::array<std::vector<double>, 3> c_;
};

}  // namespace needle_sim
