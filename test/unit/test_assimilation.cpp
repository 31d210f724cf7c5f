// Online estimation from a measured holder force (force_assimilation.hpp, doc/calibration.md
// #assimilation): twin experiments on the phantom insertion. A "patient" run with hidden values
// makes a noisy record; the estimator, started from other values, must recover them within
// its stated uncertainty, use no sample before it arrives, reject what cannot be trusted
// without being moved by it, and say when the model does not fit the stated noise.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <thread>

#include "needle_sim/calibration/force_assimilation.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;
namespace fs = std::filesystem;

namespace {
const std::string kPhantom = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml";
// The insertion only (approach, puncture, 20 mm), at 2 ms steps to keep the test short.
const std::vector<std::string> kFixed = {"time.dt=0.002", "time.duration=2.3"};
constexpr double kNoise = 5e-4;

// The hidden truth's holder force every 5th step plus N(0, noise).
ForceRecord patient(double noise, unsigned seed) {
  std::vector<std::string> sets = kFixed;
  sets.push_back("interaction.cutting_force=0.03");
  sets.push_back("interaction.grip_pressure=400");
  const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9);
  EXPECT_FALSE(f.failed);
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0, noise);
  ForceRecord r;
  for (size_t i = 4; i < f.t.size(); i += 5) {
    r.t.push_back(f.t[i]);
    r.force.push_back(f.force[i] + n(rng));
  }
  return r;
}

AssimilationSettings settings(double noise) {
  AssimilationSettings s;
  s.fit.scene = kPhantom;
  s.fit.sets = kFixed;
  s.fit.noise = noise;
  // The scene's cutting force (20 mN) is nominal; grip from 150 Pa.
  s.fit.parameters = {CalibrationParameter{"interaction.cutting_force"},
                      CalibrationParameter{"interaction.grip_pressure", 150.0, 0.0, 2000.0}};
  s.every = 0.5;
  s.predict_targets = false;
  return s;
}

ForceAssimilation runTo(const AssimilationSettings& s, const ForceRecord& data, double until) {
  ForceAssimilation a(s, data);
  for (double t = 0; t <= until + 1e-9; t += 0.002) a.advance(t);
  return a;
}
}  // namespace

// Hidden cutting 30 mN and grip 400 Pa, 0.5 mN of noise: at the end within 10 % and 3 of the
// stated standard deviations, halfway within 25 %; and causal: a checkpoint's estimate is
// bit-identical when every later sample is replaced by another patient's.
TEST(Assimilation, RecoversHiddenValuesCausally) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const ForceRecord data = patient(kNoise, 1);
  ForceAssimilation a = runTo(settings(kNoise), data, 2.3);
  a.finish(2.3);
  const auto& cps = a.checkpoints();
  ASSERT_GE(cps.size(), 4u);
  const double truth[2] = {0.03, 400};
  for (const auto& k : cps) {
    std::printf("t %.3f  samples %3d  cutting %.7f +- %.2g  grip %8.3f +- %.3g  rms %.3g mN  innovation %.3g mN  %d runs %.1f s\n", k.t,
                k.samples, k.values[0], k.stds[0], k.values[1], k.stds[1], 1e3 * k.rms, 1e3 * k.innovation_rms, k.evaluations, k.wall_s);
    EXPECT_TRUE(k.consistent);
  }
  const auto& end = cps.back();
  for (int i = 0; i < 2; ++i) {
    EXPECT_LT(std::abs(end.values[i] - truth[i]), 0.1 * truth[i]) << a.parameters()[i].key;
    EXPECT_LT(std::abs(end.values[i] - truth[i]), 3 * end.stds[i]) << a.parameters()[i].key;
  }
  // Halfway through the record (the needle is 10 mm in).
  const AssimilationCheckpoint* half = nullptr;
  for (const auto& k : cps)
    if (k.t <= 1.15 + 1e-9) half = &k;
  ASSERT_NE(half, nullptr);
  for (int i = 0; i < 2; ++i) EXPECT_LT(std::abs(half->values[i] - truth[i]), 0.25 * truth[i]) << a.parameters()[i].key;
  // The estimate improves on the nominal prediction: the innovations shrink to the noise.
  EXPECT_GT(cps.front().innovation_rms, 5 * kNoise);
  EXPECT_LT(end.innovation_rms, 1.5 * kNoise);

  // Causality: the samples after the second checkpoint replaced by another patient's.
  ForceRecord other = patient(20 * kNoise, 7);
  ForceRecord mixed = data;
  for (size_t i = 0; i < mixed.t.size(); ++i)
    if (mixed.t[i] > cps[1].t + 1e-9) mixed.force[i] = other.force[i] - 0.01;
  const ForceAssimilation b = runTo(settings(kNoise), mixed, cps[1].t);
  ASSERT_EQ(b.checkpoints().size(), 2u);
  // What it has seen: the samples up to the second checkpoint, none after it.
  for (const auto& x : b.samples()) EXPECT_EQ(x.arrived, x.t <= cps[1].t + 1e-9) << x.t;
  for (int k = 0; k < 2; ++k)
    for (int i = 0; i < 2; ++i) EXPECT_EQ(b.checkpoints()[k].values[i], cps[k].values[i]);
}

// NaN rows and stale times are skipped by the reader and counted; samples 100 x the noise off
// are rejected at the checkpoint they arrive in and counted; the estimate is then exactly the
// one from the record without them.
TEST(Assimilation, RejectsBadMeasurementsWithoutBeingMovedByThem) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const ForceRecord clean = patient(kNoise, 2);
  const fs::path csv = fs::temp_directory_path() / ("needle_sim_assim_" + std::to_string(::getpid()) + ".csv");
  ForceRecord without;  // the clean record less the samples made outliers
  {
    std::ofstream f(csv);
    f.precision(17);
    f << "t,axial_force\n";
    for (size_t i = 0; i < clean.t.size(); ++i) {
      const bool outlier = i == 40 || i == 120 || i == 200;
      f << clean.t[i] << ',' << (outlier ? clean.force[i] + (i == 120 ? -100 : 100) * kNoise : clean.force[i]) << '\n';
      if (i == 60) f << clean.t[i] + 0.001 << ",nan\n";
      if (i == 90) f << clean.t[i] << ",0.5\n";        // stale: the same time again
      if (i == 150) f << clean.t[i] + 0.001 << ",inf\n";
      if (!outlier) {
        without.t.push_back(clean.t[i]);
        without.force.push_back(clean.force[i]);
      }
    }
  }
  ForceCsvRejects rejects;
  const ForceRecord read = readForceCsv(csv.string(), &rejects);
  EXPECT_EQ(rejects.nonfinite, 2);
  EXPECT_EQ(rejects.stale, 1);
  ASSERT_EQ(read.t.size(), clean.t.size());
  ForceAssimilation a = runTo(settings(kNoise), read, 2.3);
  a.finish(2.3);
  EXPECT_EQ(a.outliers(), 3);
  ForceAssimilation b = runTo(settings(kNoise), without, 2.3);
  b.finish(2.3);
  ASSERT_EQ(a.checkpoints().size(), b.checkpoints().size());
  for (size_t k = 0; k < a.checkpoints().size(); ++k)
    for (int i = 0; i < 2; ++i) EXPECT_EQ(a.checkpoints()[k].values[i], b.checkpoints()[k].values[i]) << k;
  fs::remove(csv);
}

// Data 10 x noisier than stated: every checkpoint with enough samples says the model does not
// fit, and its standard deviations are the residuals' (not 10 x too small); stated as it is,
// none does.
TEST(Assimilation, SaysWhenTheResidualsExceedTheStatedNoise) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const ForceRecord data = patient(10 * kNoise, 3);
  AssimilationSettings s = settings(kNoise);
  s.every = 1.0;
  ForceAssimilation wrong = runTo(s, data, 2.3);
  wrong.finish(2.3);
  ASSERT_FALSE(wrong.checkpoints().empty());
  for (const auto& k : wrong.checkpoints()) EXPECT_FALSE(k.consistent) << k.t;
  s.fit.noise = 10 * kNoise;
  ForceAssimilation right = runTo(s, data, 2.3);
  right.finish(2.3);
  for (const auto& k : right.checkpoints()) EXPECT_TRUE(k.consistent) << k.t;
  // The same record: the inflated deviations are the stated-as-it-is ones to within the
  // residuals' sampling (stated 10 x too small and not inflated, they would be a tenth).
  const auto &w = wrong.checkpoints().back(), &g = right.checkpoints().back();
  ASSERT_EQ(w.stds.size(), g.stds.size());
  for (size_t i = 0; i < w.stds.size(); ++i) {
    std::printf("%s: std %.4g (stated 10 x too small, inflated) against %.4g (stated as it is)\n",
                wrong.parameters()[i].key.c_str(), w.stds[i], g.stds[i]);
    EXPECT_NEAR(w.stds[i] / g.stds[i], 1.0, 0.3) << wrong.parameters()[i].key;
  }
}

TEST(Assimilation, RejectsANoiseThatIsNotAPositiveNumber) {
  AssimilationSettings s = settings(-1.0);
  EXPECT_THROW(ForceAssimilation(s, patient(kNoise, 1)), InputError);
}

// With the targets' discretisation error asked for (run --target-error), their covariance is
// the parameters' plus diag(b^2), b the goal-oriented bound on each component at the scene's
// end (the same as a run of the estimate's own): one key gives a flat (rank-1) covariance
// from the parameters alone, a full one with the mesh's part.
TEST(Assimilation, TheTargetsCovarianceAddsTheDiscretisationBound) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const std::string target = "targets=[{name: T, point: [0.022, 0.0115, 0.0105], radius: 0.001}]";
  const ForceRecord data = patient(kNoise, 1);
  AssimilationSettings s = settings(kNoise);
  s.fit.sets.push_back(target);
  s.fit.parameters = {CalibrationParameter{"interaction.cutting_force"}};
  s.every = 1.0;
  s.predict_targets = true;
  const ForceAssimilation plain = runTo(s, data, 1.2);
  s.target_errors = true;
  const ForceAssimilation with = runTo(s, data, 1.2);
  ASSERT_EQ(plain.checkpoints().size(), 1u);
  ASSERT_EQ(with.checkpoints().size(), 1u);
  const AssimilationCheckpoint &a = plain.checkpoints()[0], &b = with.checkpoints()[0];
  EXPECT_EQ(a.values, b.values);  // the fit is the same: only the prediction run estimates
  EXPECT_TRUE(a.target_bound.empty());
  ASSERT_EQ(b.target_bound.size(), 1u);
  const Vec3 bound = b.target_bound[0];
  for (int c = 0; c < 3; ++c) EXPECT_GT(bound[c], 0.0) << c;

  // The bound is the estimate's own run's, at its end.
  std::vector<std::string> sets = s.fit.sets;
  for (const auto& o : parameterSets(with.parameters(), b.values)) sets.push_back(o);
  Simulation::Options so;
  so.target_errors = true;
  Simulation sim(loadScene(kPhantom, sets), so);
  while (sim.stepIndex() < sim.scene().numSteps()) sim.step();
  ASSERT_TRUE(sim.targetError(0).valid);
  EXPECT_EQ(sim.targetError(0).component_bound, bound);
  EXPECT_EQ(sim.targetPosition(0), b.target_end[0]);

  const Mat3 added = b.target_cov[0] - a.target_cov[0];
  EXPECT_LT((added - Mat3(bound.cwiseProduct(bound).asDiagonal())).norm(), 1e-12 * bound.squaredNorm());
  const Eigen::SelfAdjointEigenSolver<Mat3> flat(a.target_cov[0]), full(b.target_cov[0]);
  std::printf("parameters' covariance eigenvalues %.3g %.3g %.3g m^2; with the bound (%.3g, %.3g, %.3g mm) %.3g %.3g %.3g\n",
              flat.eigenvalues()[0], flat.eigenvalues()[1], flat.eigenvalues()[2], 1e3 * bound[0], 1e3 * bound[1],
              1e3 * bound[2], full.eigenvalues()[0], full.eigenvalues()[1], full.eigenvalues()[2]);
  EXPECT_LT(std::abs(flat.eigenvalues()[1]), 1e-9 * flat.eigenvalues()[2]);  // rank 1: one key
  EXPECT_GT(full.eigenvalues()[0], 0.5 * bound.cwiseProduct(bound).minCoeff());
}

namespace {
// The phantom's needle with a 30 degree bevel: the bevel's lateral load, proportional to the
// cutting force, bends the path (0.6 mm off the axis after 20 mm at 30 mN), which a tip tracker
// sees and the holder's axial force hardly does.
const std::string kBevel = "needle.bevel.angle=0.5235987755982988";
constexpr double kTipNoise = 5e-5;  // an electromagnetic tracker's 50 um per coordinate

// The hidden patient (cutting 30 mN, grip 400 Pa) every 5th step: the force and the tip, each
// with its noise.
ForceRecord bevelPatient(unsigned seed) {
  std::vector<std::string> sets = kFixed;
  sets.push_back(kBevel);
  sets.push_back("interaction.cutting_force=0.03");
  sets.push_back("interaction.grip_pressure=400");
  const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9);
  EXPECT_FALSE(f.failed);
  std::mt19937 rng(seed);
  std::normal_distribution<double> force(0, kNoise), tip(0, kTipNoise);
  ForceRecord r;
  for (size_t i = 4; i < f.t.size(); i += 5) {
    r.t.push_back(f.t[i]);
    r.force.push_back(f.force[i] + force(rng));
    r.tip.push_back(f.tip[i] + Vec3(tip(rng), tip(rng), tip(rng)));
  }
  return r;
}
}  // namespace

// A tracked tip alone (no force column: the force NaN) identifies the cutting force through
// the bevel's bending: within 10 % and 3 of its standard deviations at the end, the fit
// consistent with the tracker's stated noise; the innovations are in metres.
TEST(Assimilation, ATrackedTipAloneRecoversTheBevelsCuttingForce) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  ForceRecord data = bevelPatient(4);
  std::fill(data.force.begin(), data.force.end(), NAN);
  AssimilationSettings s = settings(NAN);
  s.fit.tip_noise = kTipNoise;
  s.fit.sets.push_back(kBevel);
  s.fit.parameters = {CalibrationParameter{"interaction.cutting_force"}};
  s.every = 0.75;
  ForceAssimilation a = runTo(s, data, 2.3);
  a.finish(2.3);
  EXPECT_STREQ(a.weights().units, "m");
  ASSERT_GE(a.checkpoints().size(), 3u);
  const auto& end = a.checkpoints().back();
  std::printf("tip alone: cutting %.6f +- %.2g (truth 0.03), rms %.3g um, first innovation %.3g um\n", end.values[0], end.stds[0],
              1e6 * end.rms, 1e6 * a.checkpoints().front().innovation_rms);
  EXPECT_LT(std::abs(end.values[0] - 0.03), 0.003);
  EXPECT_LT(std::abs(end.values[0] - 0.03), 3 * end.stds[0]);
  EXPECT_TRUE(end.consistent);
  EXPECT_LT(end.rms, 1.5 * kTipNoise);
  for (const auto& x : a.samples()) {
    EXPECT_FALSE(x.hasForce());
    EXPECT_TRUE(x.hasTip());
  }
}

// A shape sensor along the needle (a fibre-Bragg grating: the centre line every 2 mm over the
// whole 32 mm needle, 50 um per coordinate, 20 Hz) alone identifies the cutting force through
// the bevel's bending: within 10 % and 3 of its standard deviations, consistent with its
// stated noise. Its first point is the tip, so it knows at least what the tracked tip alone
// knows at the same rate and noise; the points behind it must add to that (the bend shows
// along the inserted shaft): a standard deviation below 0.8 of the tip's. (With the points
// taken from the base forward, as a PoseArray lists them, every shape is an outlier.)
TEST(Assimilation, AMeasuredShapeAloneRecoversTheBevelsCuttingForce) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  constexpr double kSpacing = 2e-3;
  constexpr size_t kPoints = 17;
  std::vector<std::string> sets = kFixed;
  sets.push_back(kBevel);
  sets.push_back("interaction.cutting_force=0.03");
  CentreLineRequest every_step;
  every_step.spacing = kSpacing;
  every_step.points = kPoints;
  const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9, nullptr, false, CommandLimits{}, nullptr, every_step);
  ASSERT_FALSE(f.failed);
  ASSERT_EQ(f.shape.size(), f.t.size());
  ASSERT_EQ(f.shape.back().size(), kPoints);
  EXPECT_NEAR((f.shape.back()[0] - f.tip.back()).norm(), 0.0, 1e-12);  // point 0: the tip
  std::mt19937 rng(7);
  std::normal_distribution<double> n(0, kTipNoise);
  ForceRecord shape, tip;
  shape.shape_spacing = kSpacing;
  for (size_t i = 24; i < f.t.size(); i += 25) {
    std::vector<Vec3> c = f.shape[i];
    for (Vec3& p : c) p += Vec3(n(rng), n(rng), n(rng));
    shape.t.push_back(f.t[i]);
    shape.force.push_back(NAN);
    shape.shape.push_back(c);
    tip.t.push_back(f.t[i]);
    tip.force.push_back(NAN);
    tip.tip.push_back(c[0]);
  }
  AssimilationSettings s = settings(NAN);
  s.fit.sets.push_back(kBevel);
  s.fit.parameters = {CalibrationParameter{"interaction.cutting_force"}};
  s.every = 2.3;
  s.fit.shape_noise = kTipNoise;
  ForceRecord unspaced = shape;
  unspaced.shape_spacing = 0;
  EXPECT_THROW(ForceAssimilation(s, unspaced), InputError);  // where its points are is unknown
  // One point 100 x its noise off: its shape rejected, the others kept.
  ForceRecord corrupted = shape;
  corrupted.shape[10][5].y() += 100 * kTipNoise;
  ForceAssimilation a = runTo(s, corrupted, 2.3);
  a.finish(2.3);
  ASSERT_EQ(a.checkpoints().size(), 1u);
  const auto& end = a.checkpoints().back();
  EXPECT_STREQ(a.weights().units, "m");
  s.fit.shape_noise = NAN;
  s.fit.tip_noise = kTipNoise;
  ForceAssimilation b = runTo(s, tip, 2.3);
  b.finish(2.3);
  ASSERT_EQ(b.checkpoints().size(), 1u);
  std::printf("shape alone: cutting %.6f +- %.2g (truth 0.03), rms %.3g um; the tip alone: +- %.2g\n", end.values[0], end.stds[0],
              1e6 * end.rms, b.checkpoints()[0].stds[0]);
  EXPECT_LT(std::abs(end.values[0] - 0.03), 0.003);
  EXPECT_LT(std::abs(end.values[0] - 0.03), 3 * end.stds[0]);
  EXPECT_TRUE(end.consistent);
  EXPECT_LT(end.rms, 1.5 * kTipNoise);
  EXPECT_LT(end.stds[0], 0.8 * b.checkpoints()[0].stds[0]);
  EXPECT_EQ(a.outliers(), 1);
  for (size_t i = 0; i < a.samples().size(); ++i) {
    const auto& x = a.samples()[i];
    EXPECT_TRUE(x.hasShape());
    EXPECT_EQ(x.shape_rejected, i == 10) << i;
    ASSERT_EQ(x.shape_predicted.size(), kPoints);
  }
}

// Both channels from a CSV, the sensors at different rates (blank cells), a tip dropout (NaN)
// and a tip 100 x its noise off: the dropout is counted by the reader, the outlier rejected at
// its checkpoint (its row's force kept), the estimate of both keys within 10 % and 3 std; both
// noises are needed to weigh the channels, and weigh them.
TEST(Assimilation, WeighsTheForceAndTheTipByTheirNoises) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const ForceRecord clean = bevelPatient(5);
  const fs::path csv = fs::temp_directory_path() / ("needle_sim_assim_tip_" + std::to_string(::getpid()) + ".csv");
  {
    std::ofstream f(csv);
    f.precision(17);
    f << "t,axial_force,tip_x,tip_y,tip_z\n";
    for (size_t i = 0; i < clean.t.size(); ++i) {
      f << clean.t[i] << ',';
      if (i % 2 == 0) f << clean.force[i];  // the force at half the tracker's rate
      Vec3 p = clean.tip[i];
      if (i == 100) p.y() += 100 * kTipNoise;
      if (i == 150) f << ",nan,nan,nan\n";
      else f << ',' << p.x() << ',' << p.y() << ',' << p.z() << '\n';
    }
  }
  ForceCsvRejects rejects;
  const ForceRecord read = readForceCsv(csv.string(), &rejects);
  fs::remove(csv);
  EXPECT_EQ(rejects.nonfinite, 1);
  ASSERT_EQ(read.t.size(), clean.t.size());  // row 150 keeps its force
  EXPECT_TRUE(std::isfinite(read.force[150]));
  EXPECT_FALSE(read.tip[150].allFinite());
  EXPECT_TRUE(std::isnan(read.force[151]));

  AssimilationSettings s = settings(kNoise);
  s.fit.sets.push_back(kBevel);
  s.every = 0.75;
  EXPECT_THROW(ForceAssimilation(s, read), InputError);  // no tip noise: cannot weigh the two
  s.fit.tip_noise = kTipNoise;
  ForceAssimilation a = runTo(s, read, 2.3);
  a.finish(2.3);
  EXPECT_STREQ(a.weights().units, "N");
  EXPECT_EQ(a.outliers(), 1);
  EXPECT_TRUE(a.samples()[100].tip_rejected);
  EXPECT_FALSE(a.samples()[100].rejected);
  const auto& end = a.checkpoints().back();
  const double truth[2] = {0.03, 400};
  for (int i = 0; i < 2; ++i) {
    std::printf("force and tip: %s %.6g +- %.3g (truth %g)\n", a.parameters()[i].key.c_str(), end.values[i], end.stds[i], truth[i]);
    EXPECT_LT(std::abs(end.values[i] - truth[i]), 0.1 * truth[i]) << a.parameters()[i].key;
    EXPECT_LT(std::abs(end.values[i] - truth[i]), 3 * end.stds[i]) << a.parameters()[i].key;
  }
  EXPECT_TRUE(end.consistent);
  // The weights act: the tracker's noise stated 10 x too small makes its residuals 10 x the
  // force's noise, and the fit inconsistent (weighed as the force, they would pass unseen).
  s.fit.tip_noise = kTipNoise / 10;
  s.every = 2.3;
  ForceAssimilation tight = runTo(s, read, 2.3);
  tight.finish(2.3);
  ASSERT_EQ(tight.checkpoints().size(), 1u);
  std::printf("tip noise stated 10 x too small: rms %.3g mN (force noise %.3g mN)\n", 1e3 * tight.checkpoints()[0].rms, 1e3 * kNoise);
  EXPECT_FALSE(tight.checkpoints()[0].consistent);
}

// The reader: a tip needs its three columns; a record needs a channel; a row with no sample
// is an error unless rejects are counted.
TEST(Assimilation, ReadsATrackedTipOrSaysWhatIsMissing) {
  const fs::path dir = fs::temp_directory_path() / ("needle_sim_assim_read_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  auto file = [&](const std::string& name, const std::string& text) {
    std::ofstream(dir / name) << text;
    return (dir / name).string();
  };
  auto column = [&](const std::string& path) {
    try {
      readForceCsv(path);
    } catch (const InputError& e) {
      return e.key();
    }
    return std::string("(none)");
  };
  EXPECT_EQ(column(file("two.csv", "t,tip_x,tip_y\n0,1,2\n1,1,2\n")), "tip_x");
  EXPECT_EQ(column(file("none.csv", "t,force\n0,1\n1,2\n")), "axial_force");
  EXPECT_EQ(column(file("empty_row.csv", "t,axial_force,tip_x,tip_y,tip_z\n0,1,,,\n1,,,,\n2,1,,,\n")), "t");
  const ForceRecord tip = readForceCsv(file("tip.csv", "t,tip_x,tip_y,tip_z\n0,1,2,3\n1,4,5,6\n"));
  ASSERT_EQ(tip.tip.size(), 2u);
  EXPECT_EQ(tip.tip[1], Vec3(4, 5, 6));
  EXPECT_FALSE(tip.hasForce());
  EXPECT_TRUE(tip.hasTip());
  ForceCsvRejects rejects;
  const ForceRecord r = readForceCsv(file("empty_row.csv", "t,axial_force,tip_x,tip_y,tip_z\n0,1,,,\n1,nan,,,\n2,1,,,\n"), &rejects);
  EXPECT_EQ(r.t.size(), 2u);
  EXPECT_EQ(rejects.nonfinite, 1);
  // A target's columns, for the targets named (the scene's); others' ignored.
  const std::string targets = file("targets.csv", "t,STN_x,STN_y,STN_z,other_x,other_y,other_z\n0,1,2,3,0,0,0\n2,4,5,6,0,0,0\n");
  EXPECT_EQ(column(targets), "axial_force");  // no target named: no channel
  const ForceRecord stn = readForceCsv(targets, nullptr, {"GPi", "STN"});
  ASSERT_EQ(stn.targets.size(), 2u);
  EXPECT_TRUE(stn.targets[0].empty());
  ASSERT_EQ(stn.targets[1].size(), 2u);
  EXPECT_EQ(stn.targets[1][1], Vec3(4, 5, 6));
  EXPECT_TRUE(stn.hasTargets());
  try {
    readForceCsv(file("stn_partial.csv", "t,STN_x,STN_y\n0,1,2\n1,1,2\n"), nullptr, {"STN"});
    ADD_FAILURE() << "two of a target's three columns accepted";
  } catch (const InputError& e) {
    EXPECT_EQ(e.key(), "STN_x");
  }
  fs::remove_all(dir);
}

// A target measured during the insertion (an image every 0.1 s, 50 um of noise) whose true
// position is the model's moved by an offset the model cannot know (0.5, -0.3, 0.2 mm: a
// registration error): the offset is estimated with the cutting force, the target's predicted
// end position (the model's plus the offset) lies within 3 of its published standard
// deviations of the truth at every checkpoint, and a target sample's innovation is taken
// against the offset estimated before it arrived.
TEST(Assimilation, AMeasuredTargetsOffsetIsEstimatedAndItsPredictionCovered) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const std::string target = "targets=[{name: T, point: [0.022, 0.0115, 0.0105], radius: 0.001}]";
  const Vec3 offset(5e-4, -3e-4, 2e-4);
  constexpr double kTargetNoise = 5e-5;
  std::vector<std::string> sets = kFixed;
  sets.push_back(target);
  sets.push_back("interaction.cutting_force=0.03");  // hidden; the grip the scene's
  const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9);
  ASSERT_FALSE(f.failed);
  ASSERT_EQ(f.targets.size(), 1u);
  const Vec3 truth_end = f.target_end[0] + offset;
  std::mt19937 rng(6);
  std::normal_distribution<double> force(0, kNoise), position(0, kTargetNoise);
  ForceRecord data;
  data.targets.resize(1);
  int images = 0;
  for (size_t i = 4; i < f.t.size(); i += 5) {
    data.t.push_back(f.t[i]);
    data.force.push_back(f.force[i] + force(rng));
    const bool image = (i - 4) % 50 == 0;
    data.targets[0].push_back(image ? Vec3(f.targets[0][i] + offset + Vec3(position(rng), position(rng), position(rng)))
                                    : Vec3::Constant(NAN));
    images += image;
  }
  AssimilationSettings s = settings(kNoise);
  s.fit.sets.push_back(target);
  s.fit.parameters = {CalibrationParameter{"interaction.cutting_force"}};
  s.predict_targets = true;
  s.every = 0.75;
  EXPECT_THROW(ForceAssimilation(s, data), InputError);  // the target's noise is needed to weigh it
  s.fit.target_noise = kTargetNoise;
  ForceAssimilation a = runTo(s, data, 2.3);
  a.finish(2.3);
  ASSERT_GE(a.checkpoints().size(), 3u);
  for (const auto& k : a.checkpoints()) {
    ASSERT_EQ(k.target_offset.size(), 1u);
    const Vec3 e = k.target_end[0] - truth_end;
    std::printf("t %.2f cutting %.5f offset (%.1f, %.1f, %.1f) um, end error (%.1f, %.1f, %.1f) um, std (%.1f, %.1f, %.1f) um\n", k.t,
                k.values[0], 1e6 * k.target_offset[0][0], 1e6 * k.target_offset[0][1], 1e6 * k.target_offset[0][2], 1e6 * e[0],
                1e6 * e[1], 1e6 * e[2], 1e6 * std::sqrt(k.target_cov[0](0, 0)), 1e6 * std::sqrt(k.target_cov[0](1, 1)),
                1e6 * std::sqrt(k.target_cov[0](2, 2)));
    for (int c = 0; c < 3; ++c) EXPECT_LT(std::abs(e[c]), 3 * std::sqrt(k.target_cov[0](c, c))) << "t " << k.t << " axis " << c;
    EXPECT_TRUE(k.consistent);
  }
  // At the end the offset's deviation is the images' noise over their number.
  const auto& end = a.checkpoints().back();
  EXPECT_NEAR(std::sqrt(end.target_cov[0](0, 0)), kTargetNoise / std::sqrt(images), 0.2 * kTargetNoise / std::sqrt(images));
  EXPECT_LT(std::abs(end.values[0] - 0.03), 0.003);
  // The first image: nothing estimated before it, so its prediction is the model's alone.
  const AssimilationSample& first = a.samples()[0];
  ASSERT_TRUE(first.hasTarget(0));
  EXPECT_LT((first.target_predicted[0] - f.targets[0][4]).norm(), 1e-5);  // the nominal model, no offset
  const AssimilationSample& later = a.samples()[200];
  ASSERT_TRUE(later.hasTarget(0));
  EXPECT_LT((later.target_measured[0] - later.target_predicted[0]).norm(), 5 * kTargetNoise);
}

// The node's way (node_assimilation.hpp): the record grows as the samples arrive (append) and
// each estimate is made when it is due (update). At the batch's checkpoint times it is the
// batch's estimate, bit for bit: the window, the warm starts and the fits are the same.
TEST(Assimilation, StreamedAsTheNodeDoesItIsTheBatchEstimate) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "calibrate's path runs under the sanitizers in test_calibration";
#endif
  const ForceRecord data = patient(kNoise, 3);
  AssimilationSettings s = settings(kNoise);
  s.fit.parameters.resize(1);  // the cutting force
  s.every = 0.7;
  ForceAssimilation batch = runTo(s, data, 2.3);
  batch.finish(2.3);
  const auto rowsIn = [&](double from, double to) {
    ForceRecord r;
    for (size_t i = 0; i < data.t.size(); ++i)
      if (data.t[i] > from + 1e-12 && data.t[i] <= to + 1e-12) {
        r.t.push_back(data.t[i]);
        r.force.push_back(data.force[i]);
      }
    return r;
  };
  std::vector<double> due;
  for (double t = data.t.front() + s.every; t <= data.t.back() + 1e-12; t += s.every) due.push_back(t);
  due.push_back(2.3);
  ForceAssimilation streamed(s, rowsIn(-1, due[0]));
  streamed.update(due[0]);
  for (size_t k = 1; k < due.size(); ++k) {
    streamed.append(rowsIn(due[k - 1], due[k]));
    streamed.update(due[k]);
  }
  ASSERT_EQ(streamed.checkpoints().size(), batch.checkpoints().size());
  ASSERT_GE(batch.checkpoints().size(), 4u);
  for (size_t k = 0; k < batch.checkpoints().size(); ++k) {
    const auto &b = batch.checkpoints()[k], &x = streamed.checkpoints()[k];
    EXPECT_EQ(x.t, b.t);
    EXPECT_EQ(x.samples, b.samples);
    EXPECT_EQ(x.values[0], b.values[0]) << "checkpoint " << k;
    EXPECT_EQ(x.stds[0], b.stds[0]) << "checkpoint " << k;
    EXPECT_EQ(x.innovation_rms, b.innovation_rms) << "checkpoint " << k;
  }
  EXPECT_NEAR(streamed.values()[0], 0.03, 0.1 * 0.03);
  // Appended rows must come after the data's end.
  EXPECT_THROW(streamed.append(rowsIn(-1, 0.1)), InputError);
}

// The node's refits of a commanded session replay the base poses its needle took at every
// step (a command received at the step's start, stamped at its end), through a command
// pipeline with the limits raised to their ceilings and no latency: that is the run itself. Checked on the
// phantom's own motion: the replay's holder force is the scene's at every step.
TEST(Assimilation, ReplayedBasePosesAreTheRunItself) {
  std::vector<std::string> sets = kFixed;
  const SimulatedForce own = simulateHolderForce(kPhantom, sets, 0, 1e9);
  ASSERT_FALSE(own.failed);
  Simulation sim(loadScene(kPhantom, sets));
  std::vector<RecordedCommand> commands;
  Observables o;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    const double start = sim.time();
    sim.step();
    observe(sim, o);
    RecordedCommand c;
    c.received = start;
    c.command.stamp = sim.time();  // reached then (no latency below)
    c.command.position = o.needles[0].base;
    c.command.orientation = o.needles[0].base_frame;
    commands.push_back(c);
  }
  CommandLimits limits;
  const LimitCeilings ceilings;
  for (const CeiledLimit& c : kCeiledLimits) limits.*c.limit = ceilings.*c.ceiling;
  limits.command_latency = 0;
  const SimulatedForce replayed = simulateHolderForce(kPhantom, sets, 0, own.t.back(), &commands, false, limits);
  ASSERT_FALSE(replayed.failed) << replayed.failure;
  ASSERT_EQ(replayed.t.size(), own.t.size());
  double peak = 0, diff = 0, tip = 0;
  for (size_t i = 0; i < own.t.size(); ++i) {
    peak = std::max(peak, std::abs(own.force[i]));
    diff = std::max(diff, std::abs(replayed.force[i] - own.force[i]));
    tip = std::max(tip, (replayed.tip[i] - own.tip[i]).norm());
  }
  std::printf("replayed base poses: holder force within %.3g N of the scene's (peak %.3g N), tip within %.3g m\n", diff,
              peak, tip);
  EXPECT_GT(peak, 0.015);
  EXPECT_LT(diff, 1e-6 * peak);
  EXPECT_LT(tip, 1e-9);
}

// The node's end (or ~reset) must not wait for a refit: a cancel set from another thread
// stops every run at its next step and calibrate() throws CalibrationCancelled, at once
// rather than after the fit's seconds.
TEST(Assimilation, ACancelledFitStopsAtItsNextStep) {
  const ForceRecord data = patient(kNoise, 5);
  std::atomic<bool> cancel{false};
  CalibrationSettings c = settings(kNoise).fit;
  c.cancel = &cancel;
  c.threads = 1;
  const auto t0 = std::chrono::steady_clock::now();
  std::thread stopper([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    cancel = true;
  });
  bool cancelled = false;
  std::string other;
  try {
    (void)calibrate(c, data);
  } catch (const CalibrationCancelled&) {
    cancelled = true;
  } catch (const std::exception& e) {
    other = e.what();
  }
  stopper.join();
  EXPECT_EQ(other, "") << "cancelled, calibrate must throw CalibrationCancelled, whenever it is";
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("cancelled after 0.3 s: calibrate returned after %.3f s\n", wall);
  EXPECT_TRUE(cancelled);
  EXPECT_LT(wall, 1.5);  // the whole fit: ~20 runs of about 0.4 s here
}
