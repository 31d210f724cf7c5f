// Calibration from a recorded insertion (force_calibration.hpp, doc/calibration.md): the
// force record's reader rejects what it cannot trust; a synthetic record made by the simulator
// itself with known values plus noise is recovered from other starting values, to within the
// standard errors the fit reports; parameters the data cannot tell apart are reported as not
// identified rather than silently fitted.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include "needle_sim/calibration/force_calibration.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"

using namespace needle_sim;
namespace fs = std::filesystem;

namespace {
const std::string kPhantom = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml";
// The insertion only (approach, puncture, 20 mm), at 2 ms steps to keep the test short.
const std::vector<std::string> kFixed = {"time.dt=0.002", "time.duration=2.3"};

fs::path writeFile(const std::string& name, const std::string& text) {
  const fs::path p = fs::temp_directory_path() / ("needle_sim_cal_" + std::to_string(::getpid()) + "_" + name);
  std::ofstream(p) << text;
  return p;
}

std::string inputErrorKey(const fs::path& p) {
  try {
    readForceCsv(p.string());
  } catch (const InputError& e) {
    return e.key().empty() ? "<file>" : e.key();
  }
  return "<accepted>";
}

// The simulator's own holder force with `truth`, every 5th step, plus Gaussian noise.
fs::path syntheticRecord(const std::vector<std::string>& truth, double noise, unsigned seed) {
  std::vector<std::string> sets = kFixed;
  sets.insert(sets.end(), truth.begin(), truth.end());
  const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9);
  EXPECT_FALSE(f.failed);
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0, noise);
  std::string csv = "t,axial_force,other\n";
  for (size_t i = 0; i < f.t.size(); i += 5) {
    char b[100];
    std::snprintf(b, sizeof b, "%.6f,%.9g,1\n", f.t[i], f.force[i] + n(rng));
    csv += b;
  }
  return writeFile("synthetic.csv", csv);
}
}  // namespace

TEST(ForceRecord, ReadsAndRejectsNamingTheColumn) {
  const ForceRecord r = readForceCsv(writeFile("ok.csv", "x,t,axial_force\n1,0.0,0.5\n2,0.1,-0.25\n\n").string());
  ASSERT_EQ(r.t.size(), 2u);
  EXPECT_EQ(r.force[1], -0.25);
  EXPECT_EQ(interpolate(r.t, r.force, 0.05), 0.125);
  EXPECT_EQ(interpolate(r.t, r.force, 9.0), -0.25);
  EXPECT_EQ(inputErrorKey(writeFile("nocol.csv", "t,force\n0,1\n1,2\n")), "axial_force");
  EXPECT_EQ(inputErrorKey(writeFile("notime.csv", "time,axial_force\n0,1\n1,2\n")), "t");
  EXPECT_EQ(inputErrorKey(writeFile("back.csv", "t,axial_force\n0,1\n1,2\n0.5,3\n")), "t");
  EXPECT_EQ(inputErrorKey(writeFile("same.csv", "t,axial_force\n0,1\n0,2\n")), "t");
  EXPECT_EQ(inputErrorKey(writeFile("nan.csv", "t,axial_force\n0,1\n1,nan\n")), "axial_force");
  EXPECT_EQ(inputErrorKey(writeFile("text.csv", "t,axial_force\n0,1\n1,abc\n")), "axial_force");
  EXPECT_EQ(inputErrorKey(writeFile("short.csv", "t,axial_force\n0,1\n1\n")), "axial_force");
  EXPECT_EQ(inputErrorKey(writeFile("one.csv", "t,axial_force\n0,1\n")), "t");
  EXPECT_EQ(inputErrorKey(writeFile("empty.csv", "")), "<file>");
  EXPECT_EQ(inputErrorKey("/nonexistent/force.csv"), "<file>");
}

TEST(Calibration, KeysTheSceneCannotFitAreInputErrors) {
  CalibrationSettings s;
  s.scene = kPhantom;
  s.sets = kFixed;
  auto keyOf = [&](const std::string& key, double start = NAN) {
    s.parameters = {CalibrationParameter{key, start}};
    try {
      resolveParameters(s);
    } catch (const InputError& e) {
      return e.key() + ": " + e.problem();
    }
    return std::string("<accepted>");
  };
  EXPECT_NE(keyOf("interaction.no_such_key", 1.0).find("interaction.no_such_key"), std::string::npos);
  EXPECT_NE(keyOf("interaction.grip_pressure").find("--start"), std::string::npos)  // absent from the file
      << keyOf("interaction.grip_pressure");
  EXPECT_NE(keyOf("solver.linear.method").find("not a number"), std::string::npos);
  EXPECT_NE(keyOf("needle.elements").find("not a real-valued key"), std::string::npos);
  EXPECT_NE(keyOf("tissue.material.young", -5).find("rejected"), std::string::npos);
  // Bounds from the scene's own checks: Poisson's ratio below 0.5, a force from 0.
  s.parameters = {CalibrationParameter{"tissue.material.poisson"}, CalibrationParameter{"interaction.cutting_force"}};
  const auto p = resolveParameters(s);
  EXPECT_EQ(p[0].start, 0.4);
  EXPECT_GT(p[0].upper, 0.49);
  EXPECT_LT(p[0].upper, 0.5);
  EXPECT_EQ(p[1].lower, 0.0);
  EXPECT_NEAR(p[1].upper, 0.02 + 10 * 0.02, 1e-15);
}

// Known values (cutting 30 mN, grip 400 Pa) with 0.5 mN of noise, fitted from (15 mN, 150 Pa).
TEST(Calibration, RecoversKnownValuesFromASyntheticRecord) {
#ifdef NEEDLE_SIM_SANITIZED
  // Under the sanitizers: the whole path (record, optimiser, penalty, threaded Jacobian) on a
  // short record with a few evaluations; the accuracy is checked in the regular build.
  const fs::path shortRecord = writeFile("short.csv", "t,axial_force\n0.1,0\n0.2,0\n0.3,-0.001\n0.4,-0.03\n");
  CalibrationSettings q;
  q.scene = kPhantom;
  q.sets = {"time.dt=0.002", "time.duration=0.4"};
  q.max_evaluations = 3;
  q.parameters = {CalibrationParameter{"interaction.cutting_force", 0.015, 0.0, 0.1}};
  const CalibrationResult rq = calibrate(q, readForceCsv(shortRecord.string()));
  EXPECT_EQ(rq.values.size(), 1u);
  EXPECT_TRUE(std::isfinite(rq.rms));
  return;
#endif
  const double noise = 5e-4;
  const fs::path data = syntheticRecord({"interaction.cutting_force=0.03", "interaction.grip_pressure=400"}, noise, 1);
  CalibrationSettings s;
  s.scene = kPhantom;
  s.sets = kFixed;
  s.parameters = {CalibrationParameter{"interaction.cutting_force", 0.015, 0.0, 0.1},
                  CalibrationParameter{"interaction.grip_pressure", 150.0, 0.0, 2000.0}};
  const CalibrationResult r = calibrate(s, readForceCsv(data.string()));
  std::printf("fit: cutting %.5f +- %.5f N, grip %.1f +- %.1f Pa; rms %.3e N (start %.3e), %d evaluations, %.1f s\n",
              r.values[0], r.std_errors[0], r.values[1], r.std_errors[1], r.rms, r.rms_start, r.evaluations, r.wall_s);
  EXPECT_EQ(r.failed_evaluations, 0);
  // The residual is the noise: the model is exact.
  EXPECT_NEAR(r.rms, noise, 0.2 * noise);
  EXPECT_GT(r.rms_start, 5 * noise);
  // What the noise alone allows, independently of the fit: the least-squares covariance
  // noise^2 (J^T J)^-1 with J the record's sensitivity at the truth (central differences of
  // the simulated record at the sampled steps). The fit must land within 3 of those standard
  // errors, and its own standard errors must be those (the fit's are from its residual and
  // its Jacobian at the fit).
  const double truth[2] = {0.03, 400};
  const char* keys[2] = {"interaction.cutting_force", "interaction.grip_pressure"};
  Eigen::MatrixXd J;
  for (int k = 0; k < 2; ++k) {
    std::vector<double> col[2];
    for (int side = 0; side < 2; ++side) {
      std::vector<std::string> sets = kFixed;
      for (int i = 0; i < 2; ++i)
        sets.push_back(std::string(keys[i]) + "=" + std::to_string(truth[i] * (i == k ? (side ? 1.02 : 0.98) : 1.0)));
      const SimulatedForce f = simulateHolderForce(kPhantom, sets, 0, 1e9);
      ASSERT_FALSE(f.failed);
      for (size_t i = 0; i < f.t.size(); i += 5) col[side].push_back(f.force[i]);
    }
    if (J.size() == 0) J.resize(static_cast<Eigen::Index>(col[0].size()), 2);
    for (size_t i = 0; i < col[0].size(); ++i) J(static_cast<Eigen::Index>(i), k) = (col[1][i] - col[0][i]) / (0.04 * truth[k]);
  }
  const Eigen::MatrixXd cov = noise * noise * (J.transpose() * J).inverse();
  for (int i = 0; i < 2; ++i) {
    const double sigma = std::sqrt(cov(i, i));
    std::printf("%s: fitted %.6g, truth %.6g, error %.2f noise standard errors (%.3g); the fit's own %.3g\n", keys[i],
                r.values[i], truth[i], (r.values[i] - truth[i]) / sigma, sigma, r.std_errors[i]);
    EXPECT_TRUE(r.identifiable[i]);
    // The phantom's force is smooth in both keys: no floor on their standard errors.
    EXPECT_LT(r.roughness[i], 1e-3) << r.parameters[i].key;
    EXPECT_LT(std::abs(r.values[i] - truth[i]), 3 * sigma) << r.parameters[i].key;
    EXPECT_GT(r.std_errors[i], 0.7 * sigma) << r.parameters[i].key;
    EXPECT_LT(r.std_errors[i], 1.4 * sigma) << r.parameters[i].key;
  }
}

// In a straight insertion friction and grip pressure enter (almost) only as their product
// mu * p: the data fix the product, not each. The fit must say so.
TEST(Calibration, ReportsParametersTheDataCannotSeparate) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "the regular build checks identifiability; the sanitizers run the path above";
#endif
  const fs::path data = syntheticRecord({"interaction.grip_pressure=400"}, 5e-4, 2);
  CalibrationSettings s;
  s.scene = kPhantom;
  s.sets = kFixed;
  s.max_evaluations = 60;
  s.parameters = {CalibrationParameter{"interaction.friction", 0.1, 0.0, 1.0},
                  CalibrationParameter{"interaction.grip_pressure", 300.0, 0.0, 2000.0}};
  const CalibrationResult r = calibrate(s, readForceCsv(data.string()));
  std::printf("fit: friction %.4f +- %.3g, grip %.1f +- %.3g Pa, product %.2f (truth 20); rms %.3e N\n", r.values[0],
              r.std_errors[0], r.values[1], r.std_errors[1], r.values[0] * r.values[1], r.rms);
  EXPECT_FALSE(r.identifiable[0] && r.identifiable[1]);
  EXPECT_NEAR(r.values[0] * r.values[1], 0.05 * 400, 0.1 * 0.05 * 400);  // the product is determined
}

// The force calibrate fits is the axial force every report gives (observables.hpp): the
// needle's force on its holder along the needle, negative while the tissue resists. The
// phantom, step by step: simulateHolderForce, observe() and the recorder's needle_axial_force
// column give the same figure, about -20 mN while the needle cuts (the tip 12-17 mm deep).
TEST(Calibration, SimulatedForceIsTheObservablesAxialForce) {
  const SimulatedForce f = simulateHolderForce(kPhantom, kFixed, 0, 2.0);
  ASSERT_FALSE(f.failed) << f.failure;
  const fs::path dir = fs::temp_directory_path() / ("needle_sim_cal_" + std::to_string(::getpid()) + "_axial");
  Simulation sim(loadScene(kPhantom, kFixed));
  std::vector<double> observed;
  {
    RunRecorder rec(sim, dir.string());
    for (size_t k = 0; k < f.t.size(); ++k) {
      rec.recordStep(sim.step(), 0.0);
      observed.push_back(observe(sim).needles[0].axial_force);
      ASSERT_EQ(sim.time(), f.t[k]);
    }
    rec.finish(0.0);
  }
  std::ifstream csv(dir / "timeseries.csv");
  std::string line;
  std::getline(csv, line);
  std::vector<std::string> header;
  std::stringstream hs(line);
  for (std::string c; std::getline(hs, c, ',');) header.push_back(c);
  const size_t col = std::find(header.begin(), header.end(), "needle_axial_force") - header.begin();
  ASSERT_LT(col, header.size()) << "no needle_axial_force column: " << line;
  double cutting = 0, calibrate_off = 0, column_off = 0;
  int n = 0, positive = 0;
  for (size_t k = 0; k < f.t.size(); ++k) {
    ASSERT_TRUE(std::getline(csv, line));
    std::stringstream row(line);
    std::string cell;
    for (size_t c = 0; c <= col; ++c) std::getline(row, cell, ',');
    calibrate_off = std::max(calibrate_off, std::abs(f.force[k] - observed[k]));
    // (the CSV holds 10 significant digits)
    column_off = std::max(column_off, std::abs(std::stod(cell) - observed[k]) - 1e-9 * std::abs(observed[k]));
    if (f.t[k] >= 1.5 && f.t[k] <= 2.0) {
      positive += f.force[k] >= 0;
      cutting += f.force[k], ++n;
    }
  }
  EXPECT_EQ(calibrate_off, 0.0) << "calibrate's simulated force is not observe()'s axial force";
  EXPECT_LE(column_off, 1e-15) << "the needle_axial_force column is not observe()'s axial force";
  ASSERT_GT(n, 200);
  EXPECT_EQ(positive, 0) << "the tissue resists the insertion: the axial force is negative while cutting";
  EXPECT_NEAR(cutting / n, -0.02, 0.005);
  fs::remove_all(dir);
}

// The roughness of a key (force_calibration.hpp): the two halves of a central difference of a
// smooth residual agree to second order (a quadratic's differ by h r''), a step between them
// (an event whose timing the key moves) makes them disagree entirely.
TEST(Calibration, RoughnessTellsAStepFromASlope) {
  const int m = 200;
  const double h = 1e-2;
  VecX r0(m), rp(m), rm(m);
  for (int i = 0; i < m; ++i) {
    const double x = i / double(m);
    // r(p) = a(x) p + b(x) p^2 at p = 1: smooth in p.
    auto r = [&](double p) { return std::sin(7 * x) * p + 0.1 * x * p * p; };
    r0[i] = r(1);
    rp[i] = r(1 + h);
    rm[i] = r(1 - h);
  }
  const double smooth = residualRoughness((rp - r0) / h, (r0 - rm) / h);
  EXPECT_GT(smooth, 0.0);
  EXPECT_LT(smooth, 0.01);  // O(h): 2 h |b| / (2 |a|)
  // An event moved past the samples 100..104 by the forward step only: a jump of 5 there.
  VecX jumped = rp;
  jumped.segment(100, 5).array() += 5.0;
  EXPECT_GT(residualRoughness((jumped - r0) / h, (r0 - rm) / h), kRoughness);
  EXPECT_NEAR(residualRoughness(VecX::Ones(3), VecX::Zero(3)), 1.0, 1e-15);
  EXPECT_EQ(residualRoughness(VecX::Zero(3), VecX::Zero(3)), 0.0);
}
