// The flagship scenes under test (issue #39, item 5): the shipped DBS scenes loaded, built and
// their brain shift solved, then the insertion, checked against facts that do not come from
// the code under test: the shift's prescribed length, the STN inside the brain, the friction
// law's share of the holder force, every constraint solve converged, and the left STN's error
// bound against a finer run (dbs_fine, kept in test/data/reference/dbs_fine_stn.csv; made by
// scripts/make_dbs_reference.sh). Forces are read through observables.hpp
// (holder_force_base), never through the recorder's columns.
//
// Cost (CTest budget of issue #39): dbs_coarse is loaded and run once, to 9 s of the
// insertion, and every test reads that run; dbs_fine and dbs_adaptive are loaded once each
// (their brain shift only).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "needle_sim/calibration/parameter_adoption.hpp"
#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/geometry/inside_test.hpp"
#include "needle_sim/needle/holder_wrench.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {

const std::string kSrc = NEEDLE_SIM_SOURCE_DIR;
const std::string kScenes = kSrc + "/config/scenes/";
const std::string kReference = kSrc + "/test/data/reference/dbs_fine_stn.csv";
const std::string kShift4mm = kSrc + "/test/data/reference/dbs_shift_4mm.csv";

// The insertion compared with the reference: the cannula from its start to 9 s (the tip near
// the left STN, the holder force at its largest), the STN's error every 50 steps.
constexpr long kLastStep = 900;
// Where the adoption tests start from a copy of the run (6 s: the cannula 30 mm into the brain).
constexpr long kAdoptStep = 600;
constexpr long kEvery = 50;

// The shift the DBS scenes prescribe for the left STN (brain_shift.target_shift) and the
// skull's gap (brain_shift.skull.gap).
constexpr double kTargetShift = 0.0065;
constexpr double kSkullGap = 0.010;

Simulation::Options withTargetErrors() {
  Simulation::Options o;
  o.target_errors = true;
  return o;
}

// The brain surface deformed with the tissue (the organ surface's vertices where the mesh
// has them now).
std::shared_ptr<const TriangleMesh> deformedBrain(const Simulation& sim) {
  std::vector<Vec3> p;
  sim.organSurface()->positions(sim.tissue().positions(), p);
  return std::make_shared<const TriangleMesh>(p, sim.organSurface()->rest().triangles());
}

// One sample of the left STN at a step: its tracked point and its error estimate.
struct StnSample {
  long step = 0;
  Vec3 position = Vec3::Zero(), qoi = Vec3::Zero();
  double bound = 0;
  bool valid = false;
  double holder_axial = 0;  // the cannula's axial holder force (base frame x) [N]
};

StnSample sampleStn(const Simulation& sim, int stn) {
  StnSample s;
  s.step = sim.stepIndex();
  s.position = sim.targetPosition(stn);
  const TargetError& e = sim.targetError(stn);
  s.valid = e.valid;
  s.qoi = e.qoi;
  s.bound = e.bound;
  s.holder_axial = observe(sim).needles[sim.findNeedle("cannula")].holder_force_base.x();
  return s;
}

// Steps `sim` to kLastStep, sampling the left STN every kEvery steps (step 0 included) and
// calling `each` after every step.
template <class Each>
std::vector<StnSample> runInsertion(Simulation& sim, Each each) {
  const int stn = sim.findTarget("STN_L");
  std::vector<StnSample> out{sampleStn(sim, stn)};
  while (sim.stepIndex() < kLastStep) {
    sim.step();
    each(sim);
    if (sim.stepIndex() % kEvery == 0) out.push_back(sampleStn(sim, stn));
  }
  return out;
}

// dbs_coarse loaded once, its brain shift kept, then stepped to kLastStep; what the tests
// read of it.
struct CoarseRun {
  std::unique_ptr<Simulation> sim;
  std::unique_ptr<Simulation> after_shift;  // a copy of sim before its first step
  std::unique_ptr<Simulation> cannula_in;   // and at kAdoptStep (the cannula in the brain)
  BrainShiftResult shift;
  Vec3 stn_rest = Vec3::Zero(), stn_shifted = Vec3::Zero(), stn_r_rest = Vec3::Zero(), stn_r_shifted = Vec3::Zero();
  // distance of the left STN to the brain surface at rest, and of the shifted one to the
  // deformed surface
  double stn_depth_rest = 0, stn_depth_after_shift = 0;
  bool stn_inside_after_shift = false, stn_r_inside_after_shift = false;
  // Each STN's error estimate of the shift (before the first step).
  TargetError shift_error_l, shift_error_r;
  std::vector<StnSample> stn;
  struct Step {
    long step;
    double axial_holder_force;  // cannula, base frame x, pushing in: negative
    double path_length;         // cannula's cut path [m]
    int constraints;            // cannula's constraint points (shaft points + tip)
    InsertionState state;
    bool converged;
    double residual;
    Vec3 tip;
  };
  std::vector<Step> steps;
  int tissue_dofs = 0;
};

const CoarseRun& coarse() {
  static const CoarseRun run = [] {
    setBlasThreads(1);
    CoarseRun r;
    r.sim = std::make_unique<Simulation>(loadScene(kScenes + "dbs_coarse.yaml"), withTargetErrors());
    Simulation& sim = *r.sim;
    r.shift = sim.brainShift();
    r.after_shift = std::make_unique<Simulation>(sim);
    r.tissue_dofs = sim.tissue().mesh().numDofs();
    const int l = sim.findTarget("STN_L"), rr = sim.findTarget("STN_R");
    r.stn_rest = sim.targetRest(l), r.stn_shifted = sim.targetPosition(l);
    r.stn_r_rest = sim.targetRest(rr), r.stn_r_shifted = sim.targetPosition(rr);
    r.shift_error_l = sim.targetError(l), r.shift_error_r = sim.targetError(rr);
    const auto brain = deformedBrain(sim);
    InsideTest in(brain);
    r.stn_inside_after_shift = in.inside(r.stn_shifted);
    r.stn_r_inside_after_shift = in.inside(r.stn_r_shifted);
    r.stn_depth_after_shift = brain->distance(r.stn_shifted);
    r.stn_depth_rest = sim.organSurface()->rest().distance(r.stn_rest);
    const int cannula = sim.findNeedle("cannula");
    Observables o;
    r.stn = runInsertion(sim, [&](const Simulation& s) {
      if (s.stepIndex() == kAdoptStep) r.cannula_in = std::make_unique<Simulation>(s);
      observe(s, o);
      const NeedleObservation& n = o.needles[cannula];
      r.steps.push_back({s.stepIndex(), n.holder_force_base.x(), n.path_length, n.constraints, n.state,
                         o.stats.constraint_converged, o.stats.constraint_residual, n.tip});
    });
    return r;
  }();
  return run;
}

// test/data/reference/dbs_fine_stn.csv: '#' lines (the first names the commit that made it),
// a header, one row per sampled step.
struct Reference {
  std::string made_by;
  std::vector<StnSample> rows;
};

// A target's position after the brain shift on the 4 mm grid (the file's row of that target:
// target,x,y,z [m]); NaN when missing.
Vec3 readShift4mm(const std::string& target) {
  std::ifstream in(kShift4mm);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#' || line.rfind("target,", 0) == 0) continue;
    std::stringstream ss(line);
    std::string name;
    Vec3 p;
    char comma = 0;
    if (std::getline(ss, name, ',') && name == target && ss >> p.x() >> comma >> p.y() >> comma >> p.z()) return p;
  }
  return Vec3::Constant(std::nan(""));
}

Reference readReference() {
  Reference ref;
  std::ifstream in(kReference);
  if (!in) return ref;
  std::string line;
  std::vector<std::string> header;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    if (line[0] == '#') {
      if (ref.made_by.empty()) ref.made_by = line;
      continue;
    }
    std::vector<std::string> cells;
    std::stringstream ss(line);
    for (std::string c; std::getline(ss, c, ',');) cells.push_back(c);
    if (header.empty()) {
      header = cells;
      continue;
    }
    std::map<std::string, double> v;
    for (size_t k = 0; k < header.size() && k < cells.size(); ++k) v[header[k]] = std::stod(cells[k]);
    StnSample s;
    s.step = static_cast<long>(v["step"]);
    s.position = Vec3(v["stn_x"], v["stn_y"], v["stn_z"]);
    s.qoi = Vec3(v["qoi_x"], v["qoi_y"], v["qoi_z"]);
    s.bound = v["bound"];
    s.valid = std::isfinite(s.bound);
    s.holder_axial = v["holder_axial"];
    ref.rows.push_back(s);
  }
  return ref;
}

}  // namespace

// The brain shift of the shipped coarse scene: the left STN moves by target_shift (the load
// is scaled for it), towards posterior (gravity, the patient supine), the skull is touched
// and not crossed, and both STNs stay inside the brain as it deformed.
TEST(DbsCoarse, BrainShiftMovesTheLeftStnByTheTargetShiftInsideTheSkull) {
  const CoarseRun& r = coarse();
  ASSERT_TRUE(r.shift.done);
  EXPECT_EQ(r.shift.target, "STN_L");
  // The length the scene prescribes, measured on the tracked point itself (not the
  // pre-step's own report), to 0.1 %.
  const Vec3 u = r.stn_shifted - r.stn_rest;
  EXPECT_NEAR(u.norm(), kTargetShift, 1e-3 * kTargetShift) << "shift " << u.transpose();
  EXPECT_NEAR(r.shift.target_displacement.norm(), kTargetShift, 1e-3 * kTargetShift);
  // Gravity is -y: the brain sinks towards posterior; most of the shift is along it.
  EXPECT_LT(u.y(), -0.8 * u.norm());
  // The load was scaled (not the unit load's shift by accident): the scale is not 1.
  EXPECT_GT(std::abs(r.shift.load_scale - 1.0), 0.1);
  // The skull: touched, crossed by at most 0.1 % of its gap.
  EXPECT_GT(r.shift.contacts, 0);
  EXPECT_LE(r.shift.max_penetration, 1e-3 * kSkullGap);
  // The CIT168 left STN's centroid, and both STNs inside the brain as it deformed.
  EXPECT_LT((r.stn_rest - Vec3(-0.0111, -0.0129, -0.0077)).norm(), 5e-4);
  EXPECT_TRUE(r.stn_inside_after_shift);
  EXPECT_TRUE(r.stn_r_inside_after_shift);
  // The STN moved with the brain around it: its depth below the surface (7.6 mm, above the
  // ventral midbrain) is kept to a fraction of the shift; a shift that moved the target but
  // not the tissue around it (or the other way round) would change it by millimetres.
  std::cout << "left STN " << r.stn_depth_rest * 1e3 << " mm below the brain's surface at rest, "
            << r.stn_depth_after_shift * 1e3 << " mm after the shift of " << u.transpose() * 1e3 << " mm (load scale "
            << r.shift.load_scale << "); skull: " << r.shift.contacts << " vertices, crossed by "
            << r.shift.max_penetration * 1e6 << " um at most\n";
  EXPECT_GT(r.stn_depth_rest, 0.005);
  EXPECT_NEAR(r.stn_depth_after_shift, r.stn_depth_rest, 0.15 * kTargetShift)
      << "depth at rest " << r.stn_depth_rest << " m";
  EXPECT_GT((r.stn_r_shifted - r.stn_r_rest).norm(), 1e-3);  // the right STN moves with the brain too
}

// A brain a hundred times softer (E = 20 Pa): linear elasticity in the corotated frame with a
// skull penalty scaled by E has the same shift under a load a hundred times smaller. The whole
// gravity moves it by metres and the first static solve fails; the pre-step starts again from
// rest at 1/8 of the load, twice, and lands on the same shift. Measured: 2 restarts, load
// scale 1.4 % above a hundredth of the scene's, the shift within 10 um of the scene's.
TEST(DbsCoarse, AHundredTimesSofterBrainShiftsAlikeUnderAHundredthOfTheLoad) {
  setBlasThreads(1);
  const Scene scene = loadScene(kScenes + "dbs_coarse.yaml");
  const double young = scene.tissue.material.young;
  Simulation soft(loadScene(kScenes + "dbs_coarse.yaml", {"tissue.material.young=" + std::to_string(young / 100)}));
  const BrainShiftResult& s = soft.brainShift();
  ASSERT_TRUE(s.done);
  EXPECT_GE(s.restarts, 1);
  EXPECT_NEAR(s.target_displacement.norm(), kTargetShift, 1e-3 * kTargetShift);
  const BrainShiftResult& stiff = coarse().shift;
  EXPECT_NEAR(s.load_scale / (stiff.load_scale / 100), 1.0, 0.03);
  EXPECT_LT((s.target_displacement - stiff.target_displacement).norm(), 5e-3 * kTargetShift);
  std::cout << "E " << young / 100 << " Pa: " << s.restarts << " restarts, load scale " << s.load_scale << " ("
            << s.load_scale / (stiff.load_scale / 100) << " of a hundredth of the scene's), shift "
            << (s.target_displacement - stiff.target_displacement).norm() * 1e6 << " um from the scene's\n";
}

// The insertion on the coarse scene: the cannula punctures and goes in; the holder's axial
// force grows with depth and is at least the grip pressure's friction on the shaft points
// (each point's friction bound is friction * (|lateral| + 2 pi r grip_pressure spacing), and
// a slipping point sits on it); no constraint solve misses its tolerance.
TEST(DbsCoarse, HolderForceGrowsWithDepthAndEveryConstraintSolveConverges) {
  const CoarseRun& r = coarse();
  const Scene& sc = r.sim->scene();
  const InteractionSettings& in = *sc.interaction;
  const double radius = sc.needles[r.sim->findNeedle("cannula")].radius;
  const double per_point = in.friction * 2 * M_PI * radius * in.grip_pressure * in.shaft_spacing;  // [N]
  ASSERT_EQ(r.steps.size(), static_cast<size_t>(kLastStep));
  int unconverged = 0;
  double worst_residual = 0;
  for (const auto& s : r.steps) {
    unconverged += s.converged ? 0 : 1;
    worst_residual = std::max(worst_residual, s.residual);
  }
  EXPECT_EQ(unconverged, 0);
  EXPECT_LE(worst_residual, in.tolerance);
  // Punctured on the way in; the cut path never longer than the cannula's advance since the
  // puncture (10 mm/s) and, at the end, most of it.
  long puncture = -1;
  for (const auto& s : r.steps)
    if (s.constraints > 0) {
      puncture = s.step;
      break;
    }
  ASSERT_GT(puncture, 0) << "the cannula never went in";
  for (const auto& s : r.steps)
    if (s.step >= puncture) {
      ASSERT_LE(s.path_length, 0.010 * (s.step - puncture + 1) * sc.dt + 1e-3) << "step " << s.step;
    }
  const CoarseRun::Step& last = r.steps.back();
  EXPECT_EQ(last.state, InsertionState::Inserted);
  EXPECT_GT(last.path_length, 0.8 * 0.010 * (kLastStep - puncture) * sc.dt);
  std::cout << "cut path " << last.path_length * 1e3 << " mm of the " << 0.010 * (kLastStep - puncture) * sc.dt * 1e3
            << " mm advanced since the puncture (step " << puncture << ")\n";
  // Mean axial force (pushing in: -x on the holder) over depth bands of one shaft spacing
  // each, from 8 mm to 40 mm: it grows from band to band.
  std::vector<double> sum(4, 0), n(4, 0);
  double worst_share = 1e300;  // the force over the grip's friction on the shaft points
  long changed = 0;             // the last step whose number of constraint points changed
  for (size_t k = 0; k < r.steps.size(); ++k) {
    const CoarseRun::Step& s = r.steps[k];
    if (k > 0 && s.constraints != r.steps[k - 1].constraints) changed = s.step;
    if (s.constraints < 2) continue;
    const int band = static_cast<int>(std::floor((s.path_length - 0.008) / 0.008));
    if (band >= 0 && band < 4) sum[band] += -s.axial_holder_force, n[band] += 1;
    // (a new point's friction builds up over its first steps, as the needle responds)
    if (s.path_length < 0.040 && s.step > changed + 2)
      worst_share = std::min(worst_share, -s.axial_holder_force / ((s.constraints - 1) * per_point));
  }
  for (int b = 0; b < 4; ++b) ASSERT_GT(n[b], 0) << "no step in band " << b;
  for (int b = 1; b < 4; ++b) EXPECT_GT(sum[b] / n[b], sum[b - 1] / n[b - 1]) << "band " << b;
  // The friction law: at least the grip's share on every shaft point (the needle's own inertia
  // aside), while the cannula slides in.
  EXPECT_GE(worst_share, 0.97) << "per point " << per_point << " N";
  // and not wildly more (the lateral forces of a straight insertion are small): a regression
  // guard on the force's size.
  double share_at_40mm = 0;
  for (const auto& s : r.steps)
    if (s.path_length >= 0.035 && s.path_length < 0.040 && s.constraints >= 2)
      share_at_40mm = -s.axial_holder_force / ((s.constraints - 1) * per_point);
  EXPECT_LT(share_at_40mm, 2.0);
  std::cout << "axial holder force by depth band (8-16, 16-24, 24-32, 32-40 mm):";
  for (int b = 0; b < 4; ++b) std::cout << " " << sum[b] / n[b];
  std::cout << " N; over the grip's share: at least " << worst_share << ", " << share_at_40mm << " at 35-40 mm\n";
}

// The left STN's error bound on dbs_coarse against the finer runs, at every sampled step to
// 9 s (the cannula at the STN). After the brain shift (step 0): against the 4 mm grid's
// shifted STN (test/data/reference/dbs_shift_4mm.csv), the bound covers the distance and is
// at most 4 times it (the sharpness goal). During the insertion: against dbs_fine
// (test/data/reference/dbs_fine_stn.csv, made by scripts/make_dbs_reference.sh at commit
// eefc828; its first line names the commit), which is no exact reference (its own shift is
// 0.77 mm from the 4 mm grid's): the bound covers the coarse-fine difference at every step,
// and where the cannula pushes the STN by millimetres (the difference above 2 mm, the fine
// run's own error a small part of it) it is at most 4 times the difference. Measured
// (2026-12-05, the sum of absolute element contributions): 3.16 mm for 1.26 mm after the
// shift (2.5x); bound / difference 1.4-1.8 where it is above 2 mm, 6-14 while the shift
// dominates (0.3-0.5 mm from dbs_fine, which is itself 0.77 mm off). The global Cauchy-Schwarz
// product (before 2026-12-05) was 17-20 mm throughout: 13x after the shift.
TEST(DbsCoarse, TargetErrorBoundCoversTheDifferenceFromFinerRunsAndIsAtMostFourTimesIt) {
  const Reference ref = readReference();
  ASSERT_FALSE(ref.rows.empty()) << kReference << " missing or empty: run scripts/make_dbs_reference.sh";
  std::cout << "reference: " << ref.made_by << "\n";
  const CoarseRun& r = coarse();
  ASSERT_EQ(r.stn.size(), ref.rows.size());
  // After the shift, against the 4 mm grid.
  const Vec3 finest = readShift4mm("STN_L");
  ASSERT_TRUE(finest.allFinite()) << kShift4mm << " missing or unreadable";
  ASSERT_EQ(r.stn[0].step, 0);
  ASSERT_TRUE(r.stn[0].valid);
  const double shift_error = (r.stn_shifted - finest).norm();
  std::cout << "after the shift: |coarse - 4 mm grid| " << shift_error * 1e3 << " mm, bound " << r.stn[0].bound * 1e3
            << " mm, ratio " << r.stn[0].bound / shift_error << "\n";
  EXPECT_GT(shift_error, 1e-4);  // the coarse mesh does not already agree
  EXPECT_GE(r.stn[0].bound, shift_error);
  EXPECT_LE(r.stn[0].bound, 4.0 * shift_error);
  // During the insertion, against dbs_fine.
  double max_diff = 0, min_diff = 1e300, max_ratio_big = 0;
  int big = 0;
  for (size_t k = 0; k < r.stn.size(); ++k) {
    const StnSample &c = r.stn[k], &f = ref.rows[k];
    ASSERT_EQ(c.step, f.step);
    ASSERT_TRUE(c.valid) << "no estimate at step " << c.step;
    ASSERT_TRUE(std::isfinite(c.bound)) << "step " << c.step;
    const double diff = (c.qoi - f.qoi).norm();
    EXPECT_GE(c.bound, diff) << "step " << c.step << ": the bound does not cover the coarse-fine difference";
    if (diff > 2e-3) {
      ++big;
      max_ratio_big = std::max(max_ratio_big, c.bound / diff);
    }
    max_diff = std::max(max_diff, diff);
    min_diff = std::min(min_diff, diff);
    std::cout << "step " << c.step << ": |coarse - fine| " << diff * 1e3 << " mm, bound " << c.bound * 1e3
              << " mm, ratio " << c.bound / diff << "; holder force coarse " << c.holder_axial << " N, fine "
              << f.holder_axial << " N\n";
  }
  // The comparison says something: the meshes differ by more than the reference's own
  // uncertainty at every step, and by millimetres where the cannula pushes the STN.
  EXPECT_GT(min_diff, 1e-4);
  EXPECT_GT(max_diff, 2e-3);
  EXPECT_GE(big, 2);
  EXPECT_LE(max_ratio_big, 4.0);
}

// The brain shift's error is that of the scaled problem (brain_shift.target_shift scales the
// load so that the left STN moves by 6.5 mm: TargetErrorEstimator::underPrescribedShift). For
// the left STN the shift's length is exact, so its estimated error has no component along the
// shift (to rounding: the dual of that component is zero by construction); the fixed-load
// estimate has one of 3.2 mm. For the right STN, whose shift follows from the scale, the
// bound covers the distance to the 4 mm grid's right STN (test/data/reference/dbs_shift_4mm.csv)
// and is at most 4 times it. Measured (2026-12-05): 6e-19 m along the shift (of an estimate
// of 0.1 mm); the right STN 1.22 mm from the 4 mm grid's, bound 4.05 mm (3.3x).
TEST(DbsCoarse, ShiftErrorIsThatOfTheScaledProblem) {
  const CoarseRun& r = coarse();
  const TargetError &l = r.shift_error_l, &rr = r.shift_error_r;
  ASSERT_TRUE(l.valid && rr.valid);
  const Vec3 d = (r.stn_shifted - r.stn_rest).normalized();
  std::cout << "STN_L: estimate " << l.estimate.transpose() * 1e3 << " mm, along the shift " << l.estimate.dot(d) * 1e3
            << " mm, bound " << l.bound * 1e3 << " mm\n";
  EXPECT_GT(l.estimate.norm(), 1e-6);  // an estimate there is
  EXPECT_LE(std::abs(l.estimate.dot(d)), 1e-9 * l.estimate.norm()) << "the prescribed target's error along its shift";
  const Vec3 finest = readShift4mm("STN_R");
  ASSERT_TRUE(finest.allFinite()) << kShift4mm << " has no STN_R row";
  const double err = (r.stn_r_shifted - finest).norm();
  std::cout << "STN_R: |coarse - 4 mm grid| " << err * 1e3 << " mm, bound " << rr.bound * 1e3 << " mm, ratio "
            << rr.bound / err << "\n";
  EXPECT_GT(err, 1e-4);  // the coarse mesh does not already agree
  EXPECT_GE(rr.bound, err);
  EXPECT_LE(rr.bound, 4.0 * err);
}

// A stiffness adopted after the brain shift (the node's estimate of tissue.material.young:
// Simulation::adopt) keeps the shift the scene prescribes: brain_shift.target_shift is a
// measured 6.5 mm, which the pre-step reaches on a stiffer brain under a proportionally larger
// load, so the shift's load scales with the stiffness in use. 0.3 s after the brain is made
// 1.5 times stiffer at once (the cannula not yet in the brain) the left STN is where the
// unadopted run's is, to 0.1 % of the shift; with the elements' stiffness changed alone (the
// load left as it was: what the comparison must tell apart) it springs back, as far as the
// skull's support springs let it. Measured (2026-12-07): 3.5e-11 m; 0.43 mm.
TEST(DbsCoarse, AStiffnessAdoptedAfterTheShiftKeepsThePrescribedShift) {
  const CoarseRun& r = coarse();
  Simulation nominal(*r.after_shift), adopted(*r.after_shift), stiffer_alone(*r.after_shift);
  const std::string key = "tissue.material.young";
  const double e = nominal.valueInUse(key);
  ASSERT_GT(e, 0);
  adopted.adopt(key, 1.5 * e);
  EXPECT_DOUBLE_EQ(adopted.valueInUse(key), 1.5 * e);
  stiffer_alone.tissue().setStiffnessScale(1.5);
  for (int k = 0; k < 30; ++k) {
    nominal.step();
    adopted.step();
    stiffer_alone.step();
  }
  const int l = nominal.findTarget("STN_L");
  const double kept = (adopted.targetPosition(l) - nominal.targetPosition(l)).norm();
  const double sprung = (stiffer_alone.targetPosition(l) - nominal.targetPosition(l)).norm();
  std::cout << "STN_L 0.3 s after 1.5x the stiffness: " << kept * 1e3 << " mm from the unadopted run's; "
            << sprung * 1e3 << " mm with the load left as it was\n";
  EXPECT_LT(kept, 1e-3 * kTargetShift);
  EXPECT_GT(sprung, 0.05 * kTargetShift);
}

// During the insertion the same stiffness, adopted over the node's ramp (0.5 s,
// ParameterAdoption as the node runs it), moves the cannula's holder force by no more in a
// step than the force sensor's noise in the DBS twin (2 mN: doc/benchmarks.md, "Assimilation")
// beyond the unadopted run's own change; adopted at once, by more. Compared over the steps
// before any of the runs lays its next shaft point (the steps in the force that each point
// makes come at other times in the three runs). Measured (2026-12-07), 41 steps: 0.70 mN
// ramped, 3.6 mN at once; the force 19 mN lower after the ramp.
TEST(DbsCoarse, AStiffnessAdoptedDuringTheInsertionChangesTheForceWithoutAJump) {
  const CoarseRun& r = coarse();
  ASSERT_TRUE(r.cannula_in);
  const std::string key = "tissue.material.young";
  Simulation nominal(*r.cannula_in), ramped(*r.cannula_in), at_once(*r.cannula_in);
  const double e = nominal.valueInUse(key);
  ParameterAdoption ramp({key}, 0.5), once({key}, 0.0);
  ramp.target(ramped, {1.5 * e});
  once.target(at_once, {1.5 * e});
  ramp.apply(ramped);
  once.apply(at_once);
  const int c = nominal.findNeedle("cannula");
  const int points = observe(nominal).needles[c].constraints;
  auto force = [&](const Simulation& s) { return observe(s).needles[c].holder_force_base.x(); };
  auto same_points = [&](const Simulation& s) { return observe(s).needles[c].constraints == points; };
  double fn = force(nominal), fr = force(ramped), fo = force(at_once);
  double jump_ramped = 0, jump_once = 0;
  int steps = 0;
  for (; steps < 70; ++steps) {
    nominal.step();
    ramped.step();
    at_once.step();
    ramp.apply(ramped);
    once.apply(at_once);
    if (!same_points(nominal) || !same_points(ramped) || !same_points(at_once)) break;
    const double n = force(nominal), a = force(ramped), o = force(at_once);
    jump_ramped = std::max(jump_ramped, std::abs((a - fr) - (n - fn)));
    jump_once = std::max(jump_once, std::abs((o - fo) - (n - fn)));
    fn = n, fr = a, fo = o;
  }
  const double change = std::abs(fr - fn);
  std::cout << steps << " steps before a new shaft point; holder force then " << fr << " N adopted over 0.5 s, " << fn
            << " N unadopted; largest step beyond the unadopted run's: " << jump_ramped * 1e3 << " mN ramped, "
            << jump_once * 1e3 << " mN at once\n";
  ASSERT_GE(steps, 30);  // most of the ramp
  EXPECT_GT(change, 0.01);  // the stiffer brain's reaction shows in the force
  EXPECT_LT(jump_ramped, 0.002);
  EXPECT_GT(jump_once, 0.002);
}

// The holder's wrench between the 10 ms steps (HolderWrenchExtrapolation, what the node
// publishes at ~wrench_rate) against the same insertion at 1 ms, every millisecond between the
// steps, from the cannula 30 mm in (6 s) to 8 s. While the cannula slides on its shaft points
// (to 7.3 s) the force changes only when a point is laid and the extrapolation holds; once the
// deepest point sticks and the force climbs with the base's advance, it follows the climb
// that holding the step's value misses (doc/benchmarks.md, "Holder force at 1 kHz").
TEST(DbsCoarse, TheHoldersWrenchBetweenStepsFollowsAOneMillisecondRun) {
  const CoarseRun& r = coarse();
  ASSERT_TRUE(r.cannula_in);
  Simulation coarse_steps(*r.cannula_in), fine_steps(*r.cannula_in);
  fine_steps.setTimeStep(0.001);
  const int c = coarse_steps.findNeedle("cannula");
  const double t0 = coarse_steps.time(), t_end = 8.0, sticks = 7.3, h = coarse_steps.dt();
  Observables o;
  std::vector<Vec3> fine;  // the 1 ms run's force on the holder after each of its steps
  while (fine_steps.time() < t_end - 1e-9) {
    fine_steps.step();
    observe(fine_steps, o);
    fine.push_back(o.needles[c].holder_force);
  }
  HolderWrenchExtrapolation w;
  auto base = [&](double t) { return coarse_steps.needle(c).trajectory().pose(t).position; };
  auto afterStep = [&] {
    observe(coarse_steps, o);
    const NeedleObservation& n = o.needles[c];
    w.afterStep(base(coarse_steps.time()), n.holder_force, n.holder_moment, n.constraints);
    return n.holder_force;
  };
  Vec3 held = afterStep();
  double sq_held[2] = {0, 0}, sq_extrapolated[2] = {0, 0};
  int samples[2] = {0, 0};
  while (coarse_steps.time() < t_end - 1e-9) {
    for (int j = 1; j < 10; ++j) {  // the milliseconds before the next step
      const double t = coarse_steps.time() + j * 0.001;
      Vec3 f, m;
      w.at(base(t), f, m);
      const Vec3& reference = fine.at(static_cast<size_t>(std::lround((t - t0) / 0.001)) - 1);
      const int phase = t > sticks ? 1 : 0;
      sq_held[phase] += (held - reference).squaredNorm();
      sq_extrapolated[phase] += (f - reference).squaredNorm();
      ++samples[phase];
    }
    coarse_steps.step();
    held = afterStep();
  }
  ASSERT_NEAR(h, 0.01, 1e-12);
  ASSERT_GT(samples[0], 500);
  ASSERT_GT(samples[1], 500);
  const double held_rms[2] = {std::sqrt(sq_held[0] / samples[0]), std::sqrt(sq_held[1] / samples[1])};
  const double extrapolated_rms[2] = {std::sqrt(sq_extrapolated[0] / samples[0]),
                                      std::sqrt(sq_extrapolated[1] / samples[1])};
  std::printf("holder force between steps against the 1 ms run, RMS [mN]: sliding held %.2f, extrapolated %.2f; "
              "sticking held %.2f, extrapolated %.2f\n",
              1e3 * held_rms[0], 1e3 * extrapolated_rms[0], 1e3 * held_rms[1], 1e3 * extrapolated_rms[1]);
  EXPECT_LT(extrapolated_rms[1], 0.8 * held_rms[1]) << "sticking: held " << 1e3 * held_rms[1] << " mN";
  EXPECT_LT(extrapolated_rms[0], 1.05 * held_rms[0]) << "sliding: held " << 1e3 * held_rms[0] << " mN";
}

// The pia is punctured at the same depth at 1 and 0.5 ms steps as at the scene's 10 ms. The
// first steps that load the tip's contact bring the brain's surface to the tip's speed (an
// inelastic impact, its force about m v / h): at 1 ms their first 14.6 mN exceeded the 10 mN
// puncture force and the cannula punctured 1 ms after the touch, 56 ms (0.56 mm) before the
// 10 ms run did; at 0.5 ms the impact spreads over two steps (18.8 and 16.0 mN).
TEST(DbsCoarse, ThePiaIsPuncturedAtTheSameDepthAtSmallerSteps) {
  const CoarseRun& r = coarse();
  const double dt = r.sim->scene().dt;
  double punctured_at = -1;
  for (const auto& s : r.steps)
    if (s.state == InsertionState::Punctured) {
      punctured_at = s.step * dt;
      break;
    }
  ASSERT_GT(punctured_at, 0);
  for (const char* step : {"0.001", "0.0005"}) {
    Simulation fine_steps(loadScene(kScenes + "dbs_coarse.yaml", {std::string("time.dt=") + step, "time.duration=1.7"}));
    const int cannula = fine_steps.findNeedle("cannula");
    double touched = -1, punctured = -1;
    while (fine_steps.stepIndex() < fine_steps.scene().numSteps() && punctured < 0) {
      fine_steps.step();
      const InsertionState st = fine_steps.interaction()->state(cannula);
      if (st == InsertionState::InContact && touched < 0) touched = fine_steps.time();
      if (st == InsertionState::Punctured) punctured = fine_steps.time();
    }
    ASSERT_GT(touched, 0) << step;
    ASSERT_GT(punctured, 0) << step;
    EXPECT_NEAR(punctured, punctured_at, dt + 1e-9) << "dt " << step << " s: touched at " << touched << " s";
    EXPECT_GT(punctured - touched, 0.03) << "dt " << step << " s";  // the tissue resisted the tip over 0.3 mm
  }
}

// dbs_fine (the reference's scene) loads, builds and shifts as prescribed, and its shifted STN
// is where the reference says: the reference is of today's code (else: regenerate it).
TEST(DbsFine, BrainShiftMatchesTheCommittedReference) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "dbs_fine.yaml"));
  ASSERT_TRUE(sim.brainShift().done);
  EXPECT_GT(sim.tissue().mesh().numDofs(), 4 * coarse().tissue_dofs);  // one uniform refinement
  const int l = sim.findTarget("STN_L");
  const Vec3 u = sim.targetPosition(l) - sim.targetRest(l);
  EXPECT_NEAR(u.norm(), kTargetShift, 1e-3 * kTargetShift);
  EXPECT_LE(sim.brainShift().max_penetration, 1e-3 * kSkullGap);
  EXPECT_TRUE(InsideTest(deformedBrain(sim)).inside(sim.targetPosition(l)));
  const Reference ref = readReference();
  ASSERT_FALSE(ref.rows.empty());
  ASSERT_EQ(ref.rows[0].step, 0);
  // 10 um: 3 % of the smallest coarse-fine difference the reference is used to measure.
  EXPECT_LT((sim.targetPosition(l) - ref.rows[0].position).norm(), 1e-5)
      << "the reference (" << ref.made_by << ") is not of this code: run scripts/make_dbs_reference.sh";
  // The coarse mesh does not already agree with the fine one (else the bound's test says
  // nothing).
  EXPECT_GT((coarse().stn_shifted - sim.targetPosition(l)).norm(), 1e-4);
}

// dbs_adaptive: the pre-step refines where the estimate asks, solves the shift again on the
// refined mesh, and keeps it, with its error bound; the shifted STN is nearer the 4 mm grid's (dbs_coarse refined
// twice, 106,947 DOFs: test/data/reference/dbs_shift_4mm.csv, which says how it was made)
// than dbs_coarse's and dbs_fine's are. dbs_fine itself is no reference for this: the shift's
// direction moves by 0.5 mm from 16 to 8 mm cells and by 0.8 mm from 8 to 4 mm (the skull
// contact and the supports' node sets change with the mesh), and the adaptive mesh, finer
// where the shift strains the brain, lands nearer the 4 mm grid. Measured: 0.38 mm from it,
// against 0.77 (dbs_fine) and 1.26 mm (dbs_coarse).
TEST(DbsAdaptive, PreStepRefinesAndComesCloserToTheFinestShift) {
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "dbs_adaptive.yaml"), withTargetErrors());
  const BrainShiftResult& s = sim.brainShift();
  ASSERT_TRUE(s.done);
  EXPECT_GE(s.passes, 2);
  EXPECT_GT(s.dofs, coarse().tissue_dofs);
  EXPECT_EQ(s.dofs, sim.tissue().mesh().numDofs());
  const int l = sim.findTarget("STN_L");
  EXPECT_NEAR((sim.targetPosition(l) - sim.targetRest(l)).norm(), kTargetShift, 1e-3 * kTargetShift);
  EXPECT_LE(s.max_penetration, 1e-3 * kSkullGap);
  const Reference ref = readReference();
  ASSERT_FALSE(ref.rows.empty());
  const Vec3 finest = readShift4mm("STN_L");
  ASSERT_TRUE(finest.allFinite()) << kShift4mm << " missing or unreadable";
  const double adaptive = (sim.targetPosition(l) - finest).norm();
  const double coarse_off = (coarse().stn_shifted - finest).norm();
  const double fine_off = (ref.rows[0].position - finest).norm();
  std::cout << "shifted STN_L from the 4 mm grid's: adaptive " << adaptive * 1e3 << " mm (" << s.dofs
            << " DOFs), dbs_fine " << fine_off * 1e3 << " mm, dbs_coarse " << coarse_off * 1e3 << " mm ("
            << coarse().tissue_dofs << " DOFs)\n";
  EXPECT_LT(adaptive, fine_off);
  EXPECT_LT(fine_off, coarse_off);
  // The shift's error bound covers the distance to the 4 mm grid. Measured: 2.56 mm for
  // 0.38 mm (6.7 times: sharper than the coarse mesh's 2.5 times it is not; doc/verification.md).
  const TargetError& e = sim.targetError(l);
  ASSERT_TRUE(e.valid);
  std::cout << "bound after the shift " << e.bound * 1e3 << " mm: " << e.bound / adaptive << " times the distance\n";
  EXPECT_GE(e.bound, adaptive);
}

// Writes the reference (scripts/make_dbs_reference.sh runs it): dbs_fine with target errors,
// stepped as the coarse run is, the left STN every 50 steps. Not run by CTest.
TEST(DbsReference, DISABLED_WriteFineReference) {
  const char* out = std::getenv("NEEDLE_SIM_DBS_REFERENCE");
  const char* commit = std::getenv("NEEDLE_SIM_DBS_REFERENCE_COMMIT");
  ASSERT_TRUE(out && commit) << "set NEEDLE_SIM_DBS_REFERENCE and NEEDLE_SIM_DBS_REFERENCE_COMMIT";
  setBlasThreads(1);
  Simulation sim(loadScene(kScenes + "dbs_fine.yaml"), withTargetErrors());
  const std::vector<StnSample> rows = runInsertion(sim, [](const Simulation&) {});
  std::ofstream f(out);
  f << "# made at commit " << commit << " by scripts/make_dbs_reference.sh (test_dbs DbsReference.DISABLED_WriteFineReference)\n"
    << "# dbs_fine.yaml (" << sim.tissue().mesh().numDofs() << " tissue DOFs), the left STN every " << kEvery
    << " steps to step " << kLastStep << ": tracked point, regularised displacement (qoi) and its error bound [m];\n"
    << "# the cannula's axial holder force (observables.hpp holder_force_base.x, pushing in: negative) [N]\n"
    << "step,stn_x,stn_y,stn_z,qoi_x,qoi_y,qoi_z,bound,holder_axial\n";
  f.precision(12);
  for (const StnSample& s : rows)
    f << s.step << "," << s.position.x() << "," << s.position.y() << "," << s.position.z() << "," << s.qoi.x() << ","
      << s.qoi.y() << "," << s.qoi.z() << "," << s.bound << "," << s.holder_axial << "\n";
  ASSERT_TRUE(f.good());
}
