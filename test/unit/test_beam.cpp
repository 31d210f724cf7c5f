// The needle: corotational Euler-Bernoulli beam and its driven base (doc/method.md, doc/verification.md).
#include <gtest/gtest.h>

#include <limits>
#include <random>

#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/needle/corotational_beam.hpp"
#include "needle_sim/needle/holder_wrench.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/needle/trajectory_replan.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {

const std::string kScenes = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/";

NeedleScene cantilever(int elements, const Vec3& dir = Vec3::UnitX()) {
  NeedleScene n;
  n.length = 0.1;
  n.radius = 0.000635;
  n.inner_radius = 0.000419;
  n.young = 2e11;
  n.poisson = 0.3;
  n.density = 8000;
  n.elements = elements;
  n.base_position = Vec3(0.01, -0.02, 0.03);
  n.base_direction = dir;
  return n;
}

SolverSettings staticSolver() {
  SolverSettings s;
  s.mode = SolverSettings::Mode::Static;
  s.static_tolerance = 1e-12;
  s.static_max_iterations = 200;
  return s;
}

double EI(const NeedleScene& n) { return n.young * BeamSection{n.radius, n.inner_radius}.secondMoment(); }

}  // namespace

TEST(BeamSection, TubeProperties) {
  const BeamSection s{2.0, 1.0};
  EXPECT_NEAR(s.area(), M_PI * 3.0, 1e-14);
  EXPECT_NEAR(s.secondMoment(), M_PI / 4 * 15.0, 1e-13);
  EXPECT_NEAR(s.polarMoment(), M_PI / 2 * 15.0, 1e-13);
}

TEST(Quaternion, ExpAndLogAreInverse) {
  for (const Vec3& v : {Vec3(1e-14, 0, 0), Vec3(1e-6, -2e-7, 3e-6), Vec3(0.3, -1.2, 0.5), Vec3(0, 0, 3.1)}) {
    EXPECT_LT((quaternionLog(quaternionExp(v)) - v).norm(), 1e-15 + 1e-13 * v.norm()) << v.transpose();
    EXPECT_NEAR(quaternionExp(v).norm(), 1.0, 1e-15);
  }
}

// Rigid motions of any size, of the rest state or of a bent state: no force from the rest
// state, and forces that rotate with the body from a bent one.
TEST(CorotationalBeam, RigidMotionGivesNoForceAndForcesRotateWithTheBody) {
  const NeedleScene n = cantilever(8);
  CorotationalBeam beam(n.elements, n.length, {n.radius, n.inner_radius}, {n.young, n.poisson, n.density},
                        n.base_position, n.base_direction);
  std::mt19937 g(3);
  std::uniform_real_distribution<double> U(-1, 1);
  // A bent, twisted, stretched state.
  BeamState bent = beam.restState();
  for (int i = 1; i < beam.numNodes(); ++i) {
    bent.p[i] += 1e-3 * Vec3(U(g), U(g), U(g));
    bent.q[i] = quaternionExp(0.05 * Vec3(U(g), U(g), U(g)));
  }
  VecX f0;
  beam.internalForce(bent, f0);
  ASSERT_GT(f0.norm(), 0);
  for (double angle : {0.3, M_PI / 2, 2.5}) {
    const Eigen::Quaterniond Q(Eigen::AngleAxisd(angle, Vec3(U(g), U(g), U(g)).normalized()));
    const Vec3 t(U(g), U(g), U(g));
    BeamState rigid = beam.restState(), moved = bent;
    for (int i = 0; i < beam.numNodes(); ++i) {
      rigid.p[i] = Q * rigid.p[i] + t;
      rigid.q[i] = Q * rigid.q[i];
      moved.p[i] = Q * moved.p[i] + t;
      moved.q[i] = Q * moved.q[i];
    }
    VecX f;
    beam.internalForce(rigid, f);
    EXPECT_LT(f.norm(), 1e-9 * f0.norm()) << angle;
    EXPECT_LT(beam.elasticEnergy(rigid), 1e-20);
    beam.internalForce(moved, f);
    VecX f0rot(f0.size());
    for (int i = 0; i < 2 * beam.numNodes(); ++i) f0rot.segment<3>(3 * i) = Q * f0.segment<3>(3 * i);
    EXPECT_LT((f - f0rot).norm(), 1e-9 * f0.norm()) << angle;
  }
}

// The internal force is minus the gradient of the elastic energy: check a directional
// derivative along positions and spins by central differences.
TEST(CorotationalBeam, ForceIsMinusEnergyGradient) {
  const NeedleScene n = cantilever(4);
  CorotationalBeam beam(n.elements, n.length, {n.radius, n.inner_radius}, {n.young, n.poisson, n.density},
                        n.base_position, n.base_direction);
  std::mt19937 g(5);
  std::uniform_real_distribution<double> U(-1, 1);
  BeamState s = beam.restState();
  for (int i = 1; i < beam.numNodes(); ++i) {
    s.p[i] += 2e-4 * Vec3(U(g), U(g), U(g));
    s.q[i] = quaternionExp(0.01 * Vec3(U(g), U(g), U(g)));
  }
  VecX f;
  beam.internalForce(s, f);
  VecX d(beam.numDofs());
  for (int i = 0; i < d.size(); ++i) d[i] = U(g) * ((i % 6) < 3 ? 1e-3 : 1e-2);
  const double h = 1e-6;
  BeamState sp = s, sm = s;
  CorotationalBeam::applyIncrement(sp, h * d);
  CorotationalBeam::applyIncrement(sm, -h * d);
  const double dE = (beam.elasticEnergy(sp) - beam.elasticEnergy(sm)) / (2 * h);
  // Small local rotations: the spin-to-rotation-vector map differs from identity at second
  // order in the local rotation (~1e-2 here), which bounds the agreement.
  EXPECT_NEAR(-f.dot(d), dE, 1e-3 * std::abs(dE));
}

struct TipLoadCase {
  int elements;
};
class TipLoad : public ::testing::TestWithParam<int> {};

// Hermite beam elements are exact for end loads: tip deflection P L^3 / 3EI, rotation
// P L^2 / 2EI; tip moment M: deflection M L^2 / 2EI, rotation M L / EI. The load is small
// (deflection 1e-5 L) so that geometric nonlinearity (relative ~ (PL^2/EI)^2) stays near
// 1e-10, and large enough that round-off in the positions (~1e-17 m) stays below 1e-11.
TEST_P(TipLoad, DeflectionAndRotationAreExact) {
  NeedleScene n = cantilever(GetParam(), Vec3(1, 2, 2) / 3.0);
  const double L = n.length, EIv = EI(n);
  const Vec3 lateral = Vec3(2, -1, 0).normalized();  // perpendicular to the axis
  const double P = 1e-5 * 3 * EIv / (L * L);
  n.tip_force = P * lateral;
  {
    NeedleBody body(n, staticSolver());
    body.solveStatic(0.0);
    const Vec3 u = body.tipPosition() - (n.base_position + L * n.base_direction);
    EXPECT_NEAR(u.dot(lateral), P * L * L * L / (3 * EIv), 1e-9 * P * L * L * L / (3 * EIv));
    const Vec3 rot = quaternionLog(body.state().q.back());
    const Vec3 axis = n.base_direction.cross(lateral);
    EXPECT_NEAR(rot.dot(axis), P * L * L / (2 * EIv), 1e-9 * P * L * L / (2 * EIv));
    // The holder balances the load: base force -P, base moment -(tip - base) x P. The base
    // force comes from the first element, whose axial force EA (l - L0) / L0 is computed
    // from positions of size |p| with relative precision eps: its round-off is about
    // EA eps |p| / L0 (1e-10 N here), which bounds the agreement besides 1e-9 P.
    const double EA = n.young * BeamSection{n.radius, n.inner_radius}.area();
    const double L0 = L / n.elements, pmax = (n.base_position + L * n.base_direction).norm();
    const double tol_f = 1e-9 * P + 4 * EA * std::numeric_limits<double>::epsilon() * pmax / L0;
    EXPECT_LT((body.baseForce() + n.tip_force).norm(), tol_f);
    EXPECT_LT((body.baseMoment() + (body.tipPosition() - n.base_position).cross(n.tip_force)).norm(), tol_f * L);
  }
  n.tip_force.setZero();
  const Vec3 axis = n.base_direction.cross(lateral);
  const double M = 2e-5 * EIv / L;
  n.tip_moment = M * axis;
  NeedleBody body(n, staticSolver());
  body.solveStatic(0.0);
  const Vec3 u = body.tipPosition() - (n.base_position + L * n.base_direction);
  EXPECT_NEAR(u.dot(lateral), M * L * L / (2 * EIv), 1e-9 * M * L * L / (2 * EIv));
  EXPECT_NEAR(quaternionLog(body.state().q.back()).dot(axis), M * L / EIv, 1e-9 * M * L / EIv);
}
INSTANTIATE_TEST_SUITE_P(Elements, TipLoad, ::testing::Values(1, 4, 20));

struct ElasticaCase {
  double alpha;  // P L^2 / EI
  double v, u, angle;  // tip deflection / L, tip shortening / L, tip rotation (rad)
};
class Elastica : public ::testing::TestWithParam<ElasticaCase> {};

// Large deflection of a cantilever under a fixed-direction tip load against the elastica
// (Bisshopp & Drucker 1945; values as tabulated by Mattiasson 1981), 20 elements, within 1 %.
TEST_P(Elastica, TwentyElementsWithinOnePercent) {
  const auto c = GetParam();
  NeedleScene n = cantilever(20);
  const double L = n.length;
  n.tip_force = Vec3(0, c.alpha * EI(n) / (L * L), 0);
  NeedleBody body(n, staticSolver());
  body.solveStatic(0.0);
  const Vec3 tip = body.tipPosition() - n.base_position;
  const double v = tip.y() / L, u = 1 - tip.x() / L;
  const double angle = quaternionLog(body.state().q.back()).z();
  EXPECT_NEAR(v, c.v, 0.01 * c.v) << "v/L " << v;
  EXPECT_NEAR(u, c.u, 0.01 * c.u) << "u/L " << u;
  EXPECT_NEAR(angle, c.angle, 0.01 * c.angle) << "angle " << angle;
}
INSTANTIATE_TEST_SUITE_P(Loads, Elastica,
                         ::testing::Values(ElasticaCase{1, 0.30172, 0.05643, 0.46135},
                                           ElasticaCase{2, 0.49346, 0.16064, 0.78175},
                                           ElasticaCase{5, 0.71379, 0.38763, 1.21537},
                                           ElasticaCase{10, 0.81061, 0.55500, 1.43029}));

// Bent through 90 degrees by a tip moment and back: the tip rotation is M L / EI exactly,
// the tip lies on the circular arc (to the chord approximation, (kappa L0)^2 / 24), and
// without the moment the needle returns to its rest shape.
TEST(CorotationalBeam, BendThroughNinetyDegreesAndBack) {
  NeedleScene n = cantilever(20);
  const double L = n.length, EIv = EI(n);
  n.tip_moment = Vec3(0, 0, M_PI / 2 * EIv / L);
  NeedleBody bent(n, staticSolver());
  bent.solveStatic(0.0);
  const double angle = quaternionLog(bent.state().q.back()).z();
  EXPECT_NEAR(angle, M_PI / 2, 1e-9);
  const double R = L / (M_PI / 2);
  const Vec3 arc_tip = n.base_position + Vec3(R, R, 0);
  EXPECT_LT((bent.tipPosition() - arc_tip).norm(), 3e-4 * L);

  n.tip_moment.setZero();
  NeedleBody back(n, staticSolver());
  back.setState(bent.state(), VecX::Zero(back.numDofs()));
  back.solveStatic(0.0);
  const BeamState rest = back.beam().restState();
  for (int i = 0; i < back.beam().numNodes(); ++i) {
    EXPECT_LT((back.state().p[i] - rest.p[i]).norm(), 1e-10 * L) << i;
    EXPECT_LT(quaternionLog(back.state().q[i]).norm(), 1e-9) << i;
  }
}

TEST(BaseTrajectory, InterpolatesPositionDirectionAndRoll) {
  BaseTrajectory tr(BasePose{Vec3(0, 0, 0), Vec3::UnitX(), 0.0});
  tr.add(1.0, BasePose{Vec3(0.02, 0, 0), Vec3::UnitX(), 0.0});
  tr.add(3.0, BasePose{Vec3(0.02, 0.01, 0), Vec3::UnitY(), 1.0});
  EXPECT_LT((tr.pose(0.5).position - Vec3(0.01, 0, 0)).norm(), 1e-15);
  const BasePose mid = tr.pose(2.0);
  EXPECT_LT((mid.position - Vec3(0.02, 0.005, 0)).norm(), 1e-15);
  EXPECT_LT((mid.direction - Vec3(1, 1, 0).normalized()).norm(), 1e-12);  // halfway round
  EXPECT_NEAR(mid.roll, 0.5, 1e-15);
  EXPECT_LT((tr.pose(10.0).position - Vec3(0.02, 0.01, 0)).norm(), 1e-15);  // held after the end
  EXPECT_LT((tr.pose(-1.0).position - Vec3::Zero()).norm(), 1e-15);
  EXPECT_THROW(tr.add(2.0, BasePose{}), std::invalid_argument);  // time going back
  EXPECT_THROW(tr.add(4.0, BasePose{Vec3::Zero(), Vec3(1, 1, 0), 0}), std::invalid_argument);  // not unit
  // Orientation: axis carried onto the commanded direction, roll about it.
  const Eigen::Quaterniond q = tr.orientation(BasePose{Vec3::Zero(), Vec3::UnitY(), M_PI / 2});
  EXPECT_LT((q * Vec3::UnitX() - Vec3::UnitY()).norm(), 1e-15);
}

namespace {
// Dynamic solver settings without damping.
SolverSettings undamped(double dt) {
  SolverSettings s;
  s.mode = SolverSettings::Mode::Dynamic;
  (void)dt;
  return s;
}
}  // namespace

// A base translating and rolling fast, the needle moving with it from the start: over
// 10,000 steps no internal force appears and nothing drifts.
TEST(NeedleDynamics, RigidBaseMotionCausesNoForceAndNoDrift) {
  NeedleScene n = cantilever(20, Vec3(0, 0.6, 0.8));
  const double h = 1e-3, T = 10.0;
  const Vec3 vel(0.05, -0.02, 0.03);  // m/s
  const double spin = 20.0;           // rad/s about the needle axis
  n.motion = {{0.0, n.base_position, n.base_direction, 0.0},
              {T, n.base_position + T * vel, n.base_direction, spin * T}};
  NeedleBody body(n, undamped(h));
  // Start with the velocity of the rigid motion (a jump from rest would be an impulse).
  VecX v0 = VecX::Zero(body.numDofs());
  for (int i = 0; i < body.beam().numNodes(); ++i) {
    v0.segment<3>(6 * i) = vel;
    v0.segment<3>(6 * i + 3) = spin * n.base_direction;
  }
  body.setState(body.state(), v0);
  const double EIv = EI(n);
  double max_energy = 0;
  for (int k = 0; k < 10000; ++k) {
    body.stepDynamic(k * h, h);
    max_energy = std::max(max_energy, body.elasticEnergy());
  }
  // Energy scale: bending the needle to a tip deflection of 1 micrometre.
  const double scale = 0.5 * 3 * EIv / std::pow(n.length, 3) * 1e-12;
  EXPECT_LT(max_energy, 1e-6 * scale);
  const Vec3 base = n.base_position + T * vel;
  EXPECT_LT((body.state().p[0] - base).norm(), 1e-12);
  EXPECT_LT((body.tipPosition() - (base + n.length * n.base_direction)).norm(), 1e-9 * n.length);
  EXPECT_LT((body.tipDirection() - n.base_direction).norm(), 1e-9);
  for (const auto& q : body.state().q) EXPECT_NEAR(q.norm(), 1.0, 1e-14);
  EXPECT_LT(body.baseForce().norm(), 1e-9);
}

// A fast swing of the base through 90 degrees and back, then rest: with damping, the needle
// settles straight on its base pose again (no drift of shape or orientation).
TEST(NeedleDynamics, FastSwingAndReturnLeavesNoDrift) {
  NeedleScene n = cantilever(20);
  const Vec3 p0 = n.base_position;
  n.motion = {{0.0, p0, Vec3::UnitX(), 0}, {0.2, p0 + Vec3(0.05, 0, 0), Vec3::UnitY(), 1.0},
              {0.4, p0, Vec3::UnitX(), 0.0}};
  SolverSettings s = undamped(1e-3);
  s.rayleigh_mass = 20.0;
  NeedleBody body(n, s);
  double max_deflection = 0;
  for (int k = 0; k < 10000; ++k) {
    body.stepDynamic(k * 1e-3, 1e-3);
    const Vec3 rel = body.tipPosition() - body.state().p[0];
    max_deflection = std::max(max_deflection, (rel - rel.dot(body.state().q[0] * Vec3::UnitX()) * (body.state().q[0] * Vec3::UnitX())).norm());
  }
  EXPECT_GT(max_deflection, 1e-4);  // the swing really bent the needle
  const BeamState rest = body.beam().restState();
  for (int i = 0; i < body.beam().numNodes(); ++i) {
    EXPECT_LT((body.state().p[i] - rest.p[i]).norm(), 1e-9 * n.length) << i;
    EXPECT_LT(quaternionLog(body.state().q[i]).norm(), 1e-8) << i;
  }
}

// Released from a bent shape without damping, implicit Euler never adds energy: the total
// energy decreases monotonically (to round-off) and the needle really oscillates.
TEST(NeedleDynamics, UndampedEnergyNeverGrows) {
  NeedleScene n = cantilever(20);
  n.tip_force = Vec3(0, 0.5 * EI(n) / (n.length * n.length), 0);  // PL^2/EI = 0.5: large bend
  NeedleBody bent(n, staticSolver());
  bent.solveStatic(0.0);
  n.tip_force.setZero();
  NeedleBody body(n, undamped(1e-4));
  body.setState(bent.state(), VecX::Zero(body.numDofs()));
  const double E0 = body.elasticEnergy();
  // First bending mode: omega = 1.875^2 sqrt(EI / (rho A L^4)), period ~ 9.4 ms = 94 steps.
  double prev = E0, min_elastic = E0, after_one_period = 0;
  for (int k = 0; k < 5000; ++k) {
    body.stepDynamic(k * 1e-4, 1e-4);
    const double E = body.elasticEnergy() + body.kineticEnergy();
    EXPECT_LE(E, prev * (1 + 1e-9)) << "step " << k;
    prev = E;
    if (k < 94) min_elastic = std::min(min_elastic, body.elasticEnergy());
    if (k == 93) after_one_period = E;
  }
  EXPECT_LT(min_elastic, 0.1 * E0);  // within a period it swung through the straight shape
  // Implicit Euler damps the mode by about (1 + (omega h)^2)^-1 per step: ~0.65 over a period.
  EXPECT_GT(after_one_period, 0.3 * E0);
  EXPECT_LT(prev, 1e-3 * E0);  // and it keeps dissipating
}

TEST(NeedleScenes, ShippedScenesRunAndTheBaseFollowsTheCommand) {
  Scene s = loadScene(kScenes + "needle_free_motion.yaml", {"time.duration=3.0"});
  Simulation sim(s);
  for (long k = 0; k < s.numSteps(); ++k) sim.step();
  // After 3 s the base has advanced 3 cm along x exactly.
  EXPECT_LT((sim.needle(0).state().p[0] - Vec3(0.03, 0, 0)).norm(), 1e-12);
  // Gravity: the holder carries the needle's weight (steady state, upward force).
  const double weight = 8000 * M_PI * (0.000635 * 0.000635 - 0.000419 * 0.000419) * 0.1 * 9.81;
  EXPECT_NEAR(sim.needle(0).baseForce().z(), weight, 1e-3 * weight);

  Scene two = loadScene(kScenes + "cannula_electrode_free.yaml", {"time.duration=0.01"});
  ASSERT_EQ(two.needles.size(), 2u);
  EXPECT_EQ(two.needles[0].name, "cannula");
  EXPECT_EQ(two.needles[1].name, "electrode");
  Simulation sim2(two);
  sim2.step();
  EXPECT_EQ(sim2.numDofs(), 6 * 25 + 6 * 29);
}

// Intraoperative re-planning (needle/trajectory_replan.hpp): the similarity about the entry
// point that carries the planned final tip onto the shifted target.
TEST(TrajectoryReplan, ReaimsAStraightInsertionThroughItsEntryPoint) {
  NeedleParameters n;
  n.length = 0.12;
  n.base_direction = Vec3(0.2, -0.4, -0.9).normalized();
  n.base_position = Vec3(-0.06, 0.07, 0.17);
  const Vec3 entry = n.base_position + n.length * n.base_direction;
  for (double a : {0.0, 0.0872}) n.motion.push_back({a * 100, n.base_position + a * n.base_direction, n.base_direction, 0.0});
  n.motion.push_back({10.0, n.base_position + 0.03 * n.base_direction, n.base_direction, 0.0});  // back out
  const Vec3 planned_tip = entry + 0.0872 * n.base_direction;  // the deepest keyframe
  const Vec3 shift(0.001, -0.002, -0.006);

  // No shift: the plan as it was.
  const NeedleParameters same = replanned(n, replanFor(n, Vec3::Zero()));
  for (size_t k = 0; k < n.motion.size(); ++k) EXPECT_LT((same.motion[k].position - n.motion[k].position).norm(), 1e-14);

  const TrajectoryReplan r = replanFor(n, shift);
  EXPECT_LT((r.entry - entry).norm(), 1e-14);
  EXPECT_LT((r.planned_tip - planned_tip).norm(), 1e-14);
  const NeedleParameters m = replanned(n, r);
  auto tip = [&](const Vec3& base, const Vec3& dir) { return Vec3(base + m.length * dir.normalized()); };
  // The rest pose keeps its tip at the entry point, the deepest tip lands on the shifted target.
  EXPECT_LT((tip(m.base_position, m.base_direction) - entry).norm(), 1e-14);
  EXPECT_LT((tip(m.motion[1].position, m.motion[1].direction) - (planned_tip + shift)).norm(), 1e-14);
  // Every keyframe's tip stays on the new straight line through the entry point, at its
  // advance times the scale, and every axis is the new line's.
  const Vec3 axis = (planned_tip + shift - entry).normalized();
  for (size_t k = 0; k < m.motion.size(); ++k) {
    const double advance = (tip(n.motion[k].position, n.motion[k].direction) - entry).norm();
    const Vec3 t = tip(m.motion[k].position, m.motion[k].direction);
    EXPECT_LT((t - (entry + r.scale * advance * axis)).norm(), 1e-14) << k;
    EXPECT_LT((m.motion[k].direction.normalized() - axis).norm(), 1e-14) << k;
    EXPECT_EQ(m.motion[k].t, n.motion[k].t);
  }
  EXPECT_NEAR(r.scale, (planned_tip + shift - entry).norm() / (planned_tip - entry).norm(), 1e-14);
  EXPECT_NEAR(r.angle(), std::acos((planned_tip - entry).normalized().dot(axis)), 1e-7);

  // A needle with no motion keeps its plan; one that never leaves its entry point cannot be
  // re-aimed.
  NeedleParameters still = n;
  still.motion.clear();
  EXPECT_EQ(replanFor(still, shift).rotation.coeffs(), Eigen::Quaterniond::Identity().coeffs());
  NeedleParameters idle = n;
  for (auto& k : idle.motion) k.position = n.base_position;
  EXPECT_THROW(replanFor(idle, shift), std::invalid_argument);
}

// Aiming a tool anew (needle/trajectory_replan.hpp rigidAim; `needle_sim check --aim`): cannula
// and electrode moved as one body so that the cannula's planned final tip (its deepest
// keyframe's, the rule of replanFor) lands on the target and its axis on entry -> target.
TEST(TrajectoryReplan, RigidAimPutsThePlannedFinalTipOnTheTarget) {
  NeedleParameters cannula;
  cannula.name = "cannula";
  cannula.length = 0.12;
  // As a scene gives it: unit to 6 digits, not exactly.
  cannula.base_direction = Vec3(0.238161, -0.414576, -0.878297);
  cannula.base_position = Vec3(-0.060446, 0.072999, 0.174282);
  for (double a : {0.0, 0.0872, 0.03})  // in, then withdrawn
    cannula.motion.push_back({a * 100, cannula.base_position + a * cannula.base_direction, cannula.base_direction, 0.0});
  NeedleParameters electrode = cannula;
  electrode.name = "electrode";
  electrode.length = 0.13;
  electrode.base_position = cannula.base_position - 0.01 * cannula.base_direction;
  for (auto& k : electrode.motion) k.position -= 0.01 * cannula.base_direction;
  const Vec3 entry(-0.036, 0.020, 0.062), target(-0.0111, -0.0129, -0.0077);
  auto tip = [](const NeedleParameters& n, int k) {
    return Vec3(n.motion[k].position + n.length * n.motion[k].direction.normalized());
  };

  const PlannedTip planned = plannedFinalTip(cannula);
  EXPECT_EQ(planned.keyframe, 1);
  EXPECT_LT((planned.tip - tip(cannula, 1)).norm(), 1e-15);
  const RigidAim aim = rigidAim(cannula, entry, target);
  const NeedleParameters c = rigidlyMoved(cannula, aim), e = rigidlyMoved(electrode, aim);
  EXPECT_LT((tip(c, 1) - target).norm(), 1e-15);
  EXPECT_LT((plannedFinalTip(c).tip - target).norm(), 1e-15);
  EXPECT_LT((c.base_direction.normalized() - (target - entry).normalized()).norm(), 1e-15);
  EXPECT_NEAR(c.base_direction.norm(), cannula.base_direction.norm(), 1e-15);  // turned, not renormalised
  // One body: the electrode keeps its place on the cannula's axis, 1 cm behind, and its tip
  // (0.13 = 0.12 + 0.01 m from its base) ends with the cannula's, to the 6 digits of the axis.
  EXPECT_LT((c.base_position - e.base_position - 0.01 * c.base_direction).norm(), 1e-15);
  EXPECT_LT((tip(e, 1) - target).norm(), 1e-7);
  for (size_t k = 0; k < c.motion.size(); ++k) EXPECT_EQ(c.motion[k].t, cannula.motion[k].t);
  EXPECT_NEAR(aim.angle(), std::acos(cannula.base_direction.normalized().dot((target - entry).normalized())), 1e-12);
  EXPECT_THROW(rigidAim(cannula, target, target), std::invalid_argument);

  // The planned final tip is the deepest keyframe's, not the largest advance's: a needle that
  // goes 10 mm in and is then pulled back 20 mm behind its start has its deepest keyframe
  // last. Its tip lands on the target; the largest advance's 30 mm away.
  NeedleParameters back = cannula;
  back.motion.clear();
  for (double a : {0.0, 0.01, -0.02})
    back.motion.push_back({std::abs(a) * 100 + back.motion.size(), back.base_position + a * back.base_direction,
                           back.base_direction, 0.0});
  EXPECT_EQ(plannedFinalTip(back).keyframe, 2);
  const NeedleParameters b = rigidlyMoved(back, rigidAim(back, entry, target));
  EXPECT_LT((tip(b, 2) - target).norm(), 1e-15);
  EXPECT_NEAR((tip(b, 1) - target).norm(), 0.03, 1e-7);

  // A full-pose keyframe (off the axis) moves with the tool too.
  NeedleParameters side = cannula;
  side.motion[1].position += Vec3(0.002, 0, 0);
  side.motion[1].direction = Vec3(0.3, -0.4, -0.866).normalized();
  const NeedleParameters s = rigidlyMoved(side, rigidAim(side, entry, target));
  EXPECT_EQ(plannedFinalTip(side).keyframe, 1);
  EXPECT_LT((tip(s, 1) - target).norm(), 1e-15);
}

// The holder's wrench between steps: a wrench linear in the base's position along its motion
// is extrapolated exactly (any point of the next step, and past it); a step that changed the
// constraint points, or a base that stood still, gives the step's wrench held.
TEST(HolderWrench, ExtrapolatesALinearLawAlongTheMotionAndHoldsAfterAnEvent) {
  const Vec3 dir = Vec3(1, -2, 2) / 3, k_f(-3, 0.5, 2), k_m(0.1, -0.2, 0.05);  // N/m, N m/m
  const Vec3 f0(0.01, 0.02, -0.03), m0(1e-3, 0, -2e-3), lateral = Vec3(2, 1, 0) / std::sqrt(5.0);
  auto force = [&](const Vec3& x) { return Vec3(f0 + k_f * dir.dot(x)); };
  auto moment = [&](const Vec3& x) { return Vec3(m0 + k_m * dir.dot(x)); };
  HolderWrenchExtrapolation w;
  Vec3 f, m;
  const double h = 1e-4;  // base advance per step [m]
  for (int step = 0; step < 3; ++step) {
    const Vec3 x = step * h * dir;
    w.afterStep(x, force(x), moment(x), 4);
  }
  ASSERT_TRUE(w.extrapolates());
  for (double s : {0.1, 0.5, 0.9, 1.0, 1.5}) {
    const Vec3 x = (2 + s) * h * dir + 3e-5 * lateral;  // off the line: only the motion's part counts
    w.at(x, f, m);
    EXPECT_NEAR((f - force(x)).norm(), 0.0, 1e-15) << s;
    EXPECT_NEAR((m - moment(x)).norm(), 0.0, 1e-15) << s;
  }
  // A shaft point laid in the step: its jump is not the motion's; held until the next step.
  const Vec3 x3 = 3 * h * dir, jump(0, 0, 0.03);
  w.afterStep(x3, force(x3) + jump, moment(x3), 5);
  EXPECT_FALSE(w.extrapolates());
  w.at(3.5 * h * dir, f, m);
  EXPECT_EQ(f, force(x3) + jump);
  EXPECT_EQ(m, moment(x3));
  // The next step without an event extrapolates again, from the new level.
  const Vec3 x4 = 4 * h * dir;
  w.afterStep(x4, force(x4) + jump, moment(x4), 5);
  w.at(4.5 * h * dir, f, m);
  EXPECT_NEAR((f - force(4.5 * h * dir) - jump).norm(), 0.0, 1e-15);
  // A base that stood still over the step: the change (a relaxation) is not the motion's.
  w.afterStep(x4, force(x4) + jump + Vec3(1e-3, 0, 0), moment(x4), 5);
  EXPECT_FALSE(w.extrapolates());
  w.at(x4 + h * dir, f, m);
  EXPECT_EQ(f, force(x4) + jump + Vec3(1e-3, 0, 0));
}
