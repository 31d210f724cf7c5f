#pragma once
// What every consumer reports about a running simulation, computed once, here: the
// recorder (timeseries.csv, summary.json), predict, the command-line tool and the ROS node
// read an Observables and its ObservableNames; none of them asks the bodies itself. Signs
// and frames (doc/method.md, "Observables"):
//   - positions in the tissue frame [m]; the needle frames in the pose convention
//     (command/pose_convention.hpp: x along the needle, towards the tip);
//   - holder force and moment: what the needle exerts on its holder (what a force/torque
//     sensor between holder and needle reads), the moment about the base node, in the tissue
//     frame and in the needle's base frame;
//   - the axial force: the one figure every report gives for "the holder force" (timeseries
//     column <needle>_axial_force, summary.json, calibrate, run --bag, the node's wrench x and
//     ~insert's feedback): the base-frame x component of the holder force, i.e. along the
//     needle towards its tip. NEGATIVE when the tissue resists an insertion (about -20 mN
//     while the phantom's needle cuts), positive when it holds a needle back that is pulled out;
//   - target displacement since step 0 (after the brain shift, if any) and shift from the
//     planning position; the distance from every needle's tip (scene order).
// observe() reuses the vectors' storage: no allocation per step once the sizes are known.
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "needle_sim/contact/needle_tissue_interaction.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

class Simulation;

struct NeedleObservation {
  Vec3 tip = Vec3::Zero(), tip_direction = Vec3::UnitX();
  Eigen::Quaterniond tip_frame = Eigen::Quaterniond::Identity();
  Vec3 base = Vec3::Zero();
  Eigen::Quaterniond base_frame = Eigen::Quaterniond::Identity();
  Vec3 holder_force = Vec3::Zero(), holder_moment = Vec3::Zero();            // tissue frame
  Vec3 holder_force_base = Vec3::Zero(), holder_moment_base = Vec3::Zero();  // base frame
  double axial_force = 0;  // holder_force_base.x(): negative when the tissue resists an insertion [N]
  InsertionState state = InsertionState::Approaching;  // Approaching without an interaction
  int constraints = 0;                                 // active constraint points
  double puncture_force = std::numeric_limits<double>::quiet_NaN();
  // The cut path (rest space, needle/tip_path.hpp): its length and the curvature of its last
  // kPathCurvatureWindow (NaN while shorter).
  double path_length = 0;
  double path_curvature = std::numeric_limits<double>::quiet_NaN();
  // A bevel tip's lateral direction (tissue frame, unit); zero for a symmetric tip.
  Vec3 bevel_direction = Vec3::Zero();
  bool inserted() const { return constraints > 0; }
};

// A needle whose tip was released (it backs off its channel) is reported withdrawing once its
// base has moved back this far since [m]; until then it is still inserted.
constexpr double kHeldStill = 1e-4;

// The stretch of the cut path whose bending observe() reports [m]: long against the shaft
// spacing (1 mm) that the path's points follow, short against a steering arc (> 20 mm radius).
constexpr double kPathCurvatureWindow = 5e-3;

struct TargetObservation {
  Vec3 position = Vec3::Zero(), velocity = Vec3::Zero();
  Vec3 displacement = Vec3::Zero();  // since step 0
  Vec3 shift = Vec3::Zero();         // from the planning position
  std::vector<double> tip_distances;  // per needle
  // The last goal-oriented estimate of the displacement's discretisation error
  // (goal_estimator.hpp), when one was computed: signed estimate of u - u_h (regularised
  // over a small ball), a bound on its norm, and the regularised displacement itself.
  bool has_error = false;
  long error_step = -1;  // the step it was computed at
  Vec3 error = Vec3::Zero();
  double error_bound = 0;
  Vec3 qoi = Vec3::Zero();
};

struct Observables {
  long step = 0;
  double time = 0;
  int dofs = 0, tissue_dofs = 0, tissue_elements = 0;
  double kinetic_energy = 0;
  std::vector<Vec3> probe_displacement;
  std::vector<NeedleObservation> needles;
  std::vector<TargetObservation> targets;
  // The last SPR estimate the simulation computed (none: has_estimate false, zeros).
  bool has_estimate = false;
  double eta_global = 0, eta_max = 0, eta_relative = 0;
  StepStats stats;  // of the last step
};

// Names (scene order: the order of every per-needle, per-probe and per-target vector above)
// and fixed values, which change only when the scene or its targets do.
struct ObservableNames {
  std::string scene;
  std::vector<std::string> needles, probes, targets;
  std::vector<Vec3> probe_rest, target_rest, target_start;
  std::vector<double> needle_radius;
};

void observe(const Simulation& sim, Observables& out);
Observables observe(const Simulation& sim);
ObservableNames observableNames(const Simulation& sim);

}  // namespace needle_sim
