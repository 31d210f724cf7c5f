// Needle-tissue interaction on the paper's phantom (8x4x4 unless stated): puncture threshold,
// friction and withdrawal, the Coulomb law on the multipliers, action = reaction, mesh
// convergence of the probe displacements.
#include <gtest/gtest.h>

#include <cstdio>
#include <map>

#include "needle_sim/contact/shaft_constraint.hpp"
#include "needle_sim/contact/tissue_surface.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {
const std::string kScene = std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_insertion_8x4x4.yaml";

Scene phantom(std::vector<std::string> sets) { return loadScene(kScene, sets); }

// The needle tilted in the x-y plane by `deg` degrees, its tip 3 mm in front of the left
// face at the centre; base motion: advance `depth` + 3 mm in T seconds while the base shifts
// `shift` sideways (bending the needle), hold, withdraw along the same path.
std::vector<std::string> tiltedInsertion(double depth, double shift, double T, double dt) {
  const double a = 5.0 * M_PI / 180;
  const Vec3 d(std::cos(a), std::sin(a), 0);
  const Vec3 tip0 = Vec3(0, 0.01, 0.01) - 0.003 * d;
  const Vec3 base0 = tip0 - 0.032 * d;
  const Vec3 base1 = base0 + (depth + 0.003) * d + Vec3(0, shift, 0);
  auto num = [](double x) {
    char b[40];
    std::snprintf(b, sizeof b, "%.17g", x);
    return std::string(b);
  };
  auto v = [&](const Vec3& p) { return "[" + num(p[0]) + "," + num(p[1]) + "," + num(p[2]) + "]"; };
  const std::string dir = v(d);
  return {"needle.base.position=" + v(base0), "needle.base.direction=" + dir,
          "needle.motion=[{t: 0, position: " + v(base0) + ", direction: " + dir + "}, {t: " + std::to_string(T) +
              ", position: " + v(base1) + ", direction: " + dir + "}, {t: " + std::to_string(T + 0.1) +
              ", position: " + v(base1) + ", direction: " + dir + "}, {t: " + std::to_string(2 * T + 0.1) +
              ", position: " + v(base0) + ", direction: " + dir + "}]",
          "time.dt=" + std::to_string(dt), "time.duration=" + std::to_string(2 * T + 0.4)};
}

const ContactConstraint* find(const Simulation& sim, ConstraintKind k) {
  for (const auto& c : sim.interaction()->constraints())
    if (c->kind() == k) return c.get();
  return nullptr;
}
}  // namespace

// Pressed on the surface below the puncture strength, the needle indents the tissue and,
// withdrawn, leaves it as it was; no constraint work is done before contact.
TEST(Interaction, BelowPunctureForceIndentsAndComesBack) {
  Simulation sim(phantom({"interaction.puncture_force=100",
                          "needle.motion=[{t: 0, advance: 0}, {t: 0.31, advance: 0.00305}, {t: 0.62, advance: 0}]",
                          "time.duration=1.2"}));
  double max_push = 0, max_force = 0;
  bool contact = false;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    const StepStats& st = sim.step();
    const auto s = sim.interaction()->state(0);
    ASSERT_NE(s, InsertionState::Punctured);
    ASSERT_NE(s, InsertionState::Inserted);
    if (st.constraint_points == 0) {
      EXPECT_EQ(st.constraint_iterations, 0);  // nothing to solve: skipped
    }
    if (const auto* c = find(sim, ConstraintKind::Puncture)) {
      contact = true;
      max_force = std::max(max_force, c->lambda[0]);
    }
    max_push = std::max(max_push, sim.probeDisplacement(0).x());
  }
  EXPECT_TRUE(contact);
  EXPECT_GT(max_force, 0.05);
  EXPECT_GT(max_push, 1e-7);  // the tissue was pushed in along the needle
  EXPECT_EQ(sim.interaction()->state(0), InsertionState::Approaching);
  EXPECT_LT(sim.probeDisplacement(0).norm(), 1e-3 * max_push);
}

// Before the puncture the holder feels the tissue's deformation: the contact force against the
// indentation of the tissue's contact point follows the stiffness the mesh gives to a point
// load there (1 / its static compliance, computed on a copy of the tissue at rest). On two
// meshes, whose stiffnesses differ, the force profile follows each one's.
TEST(Interaction, ForceBeforePunctureFollowsTheMeshStiffness) {
  std::vector<double> stiffness;
#ifdef NEEDLE_SIM_SANITIZED
  // 19x slower under the sanitizers: the coarse mesh only (the same code).
  const std::vector<const char*> grids = {"[8,4,4]"};
#else
  const std::vector<const char*> grids = {"[8,4,4]", "[16,8,8]"};
#endif
  for (const char* cells : grids) {
    SCOPED_TRACE(cells);
    // The tip 3 mm in front of the surface: 2.9 mm quickly, then 0.2 mm/s (quasi-static:
    // the tissue's inertia and damping are below 0.5 % of its elastic force); never punctures.
    Simulation sim(phantom({"interaction.puncture_force=100", std::string("tissue.grid.cells=") + cells,
                            "needle.motion=[{t: 0, advance: 0}, {t: 0.5, advance: 0.0029}, {t: 1.5, advance: 0.0031}]",
                            "time.duration=1.5"}));
    const TissueBody rest = sim.tissue();
    const ContactConstraint* c = nullptr;
    std::vector<double> force, indentation;
    for (long k = 0; k < sim.scene().numSteps(); ++k) {
      sim.step();
      ASSERT_NE(sim.interaction()->state(0), InsertionState::Punctured);
      if (!(c = find(sim, ConstraintKind::Puncture))) continue;
      const Vec3 n = c->frame.col(0);  // outward normal; the tissue is pushed along -n
      const Vec3 u = c->tissue.interpolate(sim.tissue().mesh(), sim.tissue().displacements());
      force.push_back(c->lambda[0]);
      indentation.push_back(-n.dot(u));
    }
    ASSERT_GT(force.size(), 200u);
    ASSERT_GT(force.back(), 0.1);
    // The mesh's stiffness at that material point: a unit load into the tissue, static.
    TissueBody t = rest;
    const Vec3 n = c->frame.col(0);
    VecX f = VecX::Zero(t.mesh().numNodes() * 3);
    for (int a = 0; a < 8; ++a) f.segment<3>(3 * t.mesh().element(c->tissue.element)[a]) -= c->tissue.weights[a] * n;
    t.addExternalForce(f);
    t.solveStatic();
    const double compliance = -n.dot(c->tissue.interpolate(t.mesh(), t.displacements()));
    ASSERT_GT(compliance, 0);
    // The slope of force against indentation over the second half of the contact.
    double fd = 0, dd = 0;
    for (size_t i = force.size() / 2; i < force.size(); ++i) fd += force[i] * indentation[i], dd += indentation[i] * indentation[i];
    const double slope = fd / dd;
    std::printf("  %s: contact force %.3f N at %.3g m of indentation; slope %.5g N/m, mesh stiffness %.5g N/m\n", cells,
                force.back(), indentation.back(), slope, 1 / compliance);
    EXPECT_NEAR(slope * compliance, 1.0, 0.01);
    stiffness.push_back(1 / compliance);
  }
  if (stiffness.size() == 2) {
    EXPECT_GT(std::abs(stiffness[0] / stiffness[1] - 1), 0.05) << "the two meshes must differ for the check to mean anything";
  }
}

// A puncture strength 100 times the needle's Euler load (the stability sweep's 10 N case):
// the needle buckles, its tip slides along the face it touched, off the edge and onto the
// next face, and never enters the tissue without a puncture. (Before, the contact was
// released at the edge or when the force vanished, and the straightening needle's tip
// swept into the block unnoticed.)
namespace {
struct BuckledRun {
  double deepest = 0, umax = 0, lateral = 0;  // [m]
  Vec3 tip = Vec3::Zero();                    // at the end
};
// tilt: the needle's axis turned up (+z) by this angle [rad], so that it buckles towards the
// top face whatever the rounding (untilted, the direction it buckles to depends on the BLAS
// kernels' rounding).
BuckledRun buckled(double tilt) {
  Simulation sim(phantom({"interaction.puncture_force=10", "interaction.cutting_force=10",
                          "needle.motion=[{t: 0, advance: 0}, {t: 1.3, advance: 0.013}]", "time.duration=1.6",
                          "needle.base.direction=[" + std::to_string(std::cos(tilt)) + ", 0, " +
                              std::to_string(std::sin(tilt)) + "]"}));
  BuckledRun r;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    sim.step();
    const auto s = sim.interaction()->state(0);
    EXPECT_NE(s, InsertionState::Punctured) << k;
    EXPECT_NE(s, InsertionState::Inserted) << k;
    const Vec3 tip = sim.needle(0).tipPosition();
    // Depth inside the block at rest (0..40 x 0..20 x 0..20 mm): the smallest distance to a face.
    const double depth = std::min({tip.x(), 0.04 - tip.x(), tip.y(), 0.02 - tip.y(), tip.z(), 0.02 - tip.z()});
    r.deepest = std::max(r.deepest, depth);
    r.umax = std::max(r.umax, sim.tissue().displacements().lpNorm<Eigen::Infinity>());
    r.lateral = std::max(r.lateral, std::hypot(tip.y() - 0.01, tip.z() - 0.01));
  }
  r.tip = sim.needle(0).tipPosition();
  return r;
}
}  // namespace

TEST(Interaction, ABuckledTipSlidesOnTheSurfaceAndNeverPassesThroughIt) {
  const BuckledRun r = buckled(0);
  EXPECT_GT(r.lateral, 0.01);  // it buckled off the axis, past the face's edge
  EXPECT_LT(r.deepest, r.umax + 1e-4) << "the tip entered the tissue unpunctured";
}

// Tilted up or down by 0.05 rad, the buckled tip slides up (down) the entry face, over the
// edge, and 8 mm along the top (bottom) face, on it. Before the contact kept to the face
// under a tip past an edge, it chattered between the two faces at the edge and fell 7.9 mm
// into the block.
TEST(Interaction, ABuckledTipSlidesOverTheEdgeOntoTheNextFace) {
  for (double tilt : {0.05, -0.05}) {
    SCOPED_TRACE(tilt);
    const BuckledRun r = buckled(tilt);
    EXPECT_LT(r.deepest, r.umax + 1e-4) << "the tip entered the tissue unpunctured";
    EXPECT_GT(r.tip.x(), 0.005);                                         // along the next face
    EXPECT_NEAR(r.tip.z(), tilt > 0 ? 0.02 : 0.0, r.umax + 1e-5);         // on it
  }
}

// Pulled back 2 mm and pushed on: the tip leaves its channel's end (withdrawing, shaft points
// only), slides back along its own channel, and past the end it cuts again (a tip constraint
// there, new shaft points beyond the old path), instead of passing through uncut tissue.
TEST(Interaction, ReinsertedPastItsPathEndTheTipCutsOn) {
  Simulation sim(phantom({"needle.motion=[{t: 0, advance: 0}, {t: 1.3, advance: 0.013}, {t: 1.5, advance: 0.011}, "
                          "{t: 2.1, advance: 0.017}]",
                          "time.duration=2.1"}));
  bool withdrew = false, cut_again = false;
  int points_at_turn = 0;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    sim.step();
    const auto s = sim.interaction()->state(0);
    if (sim.time() <= 1.3 + 1e-9) points_at_turn = sim.interaction()->activePoints(0);
    if (s == InsertionState::Withdrawing) withdrew = true;
    if (withdrew && s == InsertionState::Inserted && find(sim, ConstraintKind::Tip)) cut_again = true;
  }
  EXPECT_TRUE(withdrew);
  EXPECT_TRUE(cut_again);
  EXPECT_EQ(sim.interaction()->state(0), InsertionState::Inserted);
  ASSERT_NE(find(sim, ConstraintKind::Tip), nullptr);
  // Shaft points every millimetre: about four more than at the turn (13 -> 17 mm).
  EXPECT_GE(sim.interaction()->activePoints(0), points_at_turn + 3);
}

// Above the strength: puncture, at a force equal to the threshold within one step's increase.
TEST(Interaction, PunctureHappensAtTheThreshold) {
  Simulation sim(phantom({"time.duration=0.5"}));
  std::vector<double> forces;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    sim.step();
    if (const auto* c = find(sim, ConstraintKind::Puncture)) forces.push_back(c->lambda[0]);
    if (sim.interaction()->state(0) == InsertionState::Punctured) break;
  }
  ASSERT_EQ(sim.interaction()->state(0), InsertionState::Punctured);
  const double threshold = sim.scene().interaction->puncture_force;
  const double fp = sim.interaction()->punctureForce(0);
  ASSERT_GE(forces.size(), 1u);
  const double before = forces.size() >= 2 ? forces[forces.size() - 2] : 0.0;  // last force in contact
  EXPECT_GE(fp, threshold);
  EXPECT_LT(before, threshold);
  EXPECT_LE(fp - threshold, fp - before);  // within one step's increment
  EXPECT_NE(find(sim, ConstraintKind::Tip), nullptr);
}

// A soft tissue pressed at a surface node dents into a cone of facets; the contact normal is
// the smoothed one (tissue_surface.hpp), so the tip punctures where the needle aims. With the
// facet normals, 1 um off the node the tip was pushed 0.2-0.5 mm sideways before it punctured
// (0.47 mm at this tissue on the default element).
TEST(Interaction, ASoftTissueIsPuncturedWhereTheNeedleAimsAtANode) {
  for (const Vec3& off : {Vec3(0, 0, 1e-6), Vec3(0, -1e-6, 2e-6), Vec3(0, 4e-4, -3e-4)}) {
    const Vec3 base = Vec3(-0.035, 0.01, 0.01) + off;
    char pos[120];
    std::snprintf(pos, sizeof pos, "needle.base.position=[%.17g,%.17g,%.17g]", base[0], base[1], base[2]);
    Simulation sim(phantom({"tissue.material.young=6000", pos, "time.duration=0.9"}));
    for (long k = 0; k < sim.scene().numSteps() && sim.interaction()->state(0) != InsertionState::Punctured; ++k)
      sim.step();
    ASSERT_EQ(sim.interaction()->state(0), InsertionState::Punctured) << off.transpose();
    const Vec3 entry = sim.interaction()->cutPath(0).front();  // rest coordinates
    EXPECT_NEAR(entry[0], 0.0, 1e-12);
    EXPECT_NEAR((entry - Vec3(0, 0.01, 0.01) - off).norm(), 0.0, 2e-6) << "aimed " << off.transpose() * 1e3
                                                                        << " mm, punctured " << entry.transpose() * 1e3;
  }
}

// The smoothed normal on a dented box face: along the dent's axis at its node, turning
// continuously off it (not by the facets' slope); a box's edge stays sharp.
TEST(TissueSurfaceNormal, IsTheDentsAxisAtItsNodeAndTheFaceNormalAtAnEdge) {
  const HexMesh mesh = HexMesh::box(Vec3(0, 0, 0), Vec3(0.02, 0.02, 0.02), Vec3i(2, 2, 2));
  const TissueSurface surface(mesh);
  VecX x(3 * mesh.numNodes());
  int centre = -1;
  for (int i = 0; i < mesh.numNodes(); ++i) {
    x.segment<3>(3 * i) = mesh.node(i);
    if ((mesh.node(i) - Vec3(0, 0.01, 0.01)).norm() < 1e-12) centre = i;
  }
  ASSERT_GE(centre, 0);
  x[3 * centre] += 0.002;  // a dent 2 mm deep in a 10 mm cell: facets turned by 11 degrees
  auto normalAt = [&](double y, double z) {
    SurfaceHit hit;
    EXPECT_TRUE(surface.firstEntry(x, Vec3(-0.01, y, z), Vec3(0.01, y, z), hit));
    return hit.normal;
  };
  EXPECT_NEAR((normalAt(0.01, 0.01) - Vec3(-1, 0, 0)).norm(), 0.0, 1e-12);
  // 1 um off the node: turned by about 1e-6 / 0.01 of the dent's slope, not by 11 degrees.
  for (const auto& [y, z] : {std::pair{0.01, 0.010001}, {0.009999, 0.01}, {0.010001, 0.009999}})
    EXPECT_LT((normalAt(y, z) - Vec3(-1, 0, 0)).norm(), 1e-4) << y << " " << z;
  // Off the node, it tilts towards the dent's axis (outward and inward of the dent).
  const Vec3 n = normalAt(0.01, 0.015);
  EXPECT_LT(n[2], -0.01);
  EXPECT_NEAR(n.norm(), 1.0, 1e-12);
  // Near a box's edge (the face x = 0 meets y = 0), the face's own normal.
  x[3 * centre] -= 0.002;
  EXPECT_NEAR((normalAt(1e-6, 0.005) - Vec3(-1, 0, 0)).norm(), 0.0, 1e-12);
}

namespace {
struct WithdrawalRun {
  double max_disp = 0;           // largest probe displacement during the run
  Vec3 disp_end_hold = Vec3::Zero();
  Vec3 disp_withdrawn = Vec3::Zero();
  double push = 0, pull = 0;     // base force along the axis: max while inserting, min while withdrawing
  double min_axial_withdrawal = 0;  // probe displacement along the axis while withdrawing (dragged out: < 0)
  int max_points = 0;
  double max_cone_violation = 0; // shaft points: |lambda_ax| - mu |lambda_lat|
  int slips = 0, slips_on_cone = 0;
  double max_force_imbalance = 0;
};

WithdrawalRun insertAndWithdraw(double friction) {
  const double T = 1.3, dt = 0.002;
  auto sets = tiltedInsertion(0.01, 0.001, T, dt);
  sets.push_back("interaction.friction=" + std::to_string(friction));
  Simulation sim(phantom(sets));
  const Vec3 axis = sim.scene().needles[0].base_direction;
  WithdrawalRun r;
  const double mu = friction;
  std::map<const ContactConstraint*, std::pair<double, Vec3>> last;  // s and lambda of the previous step
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    const double t = sim.time();
    sim.step();
    const auto* in = sim.interaction();
    // The probe nearest the path, 2.5 mm deep.
    const Vec3 u = sim.probeDisplacement(0);
    r.max_disp = std::max(r.max_disp, u.norm());
    if (std::abs(t - (T + 0.1)) < dt / 2) r.disp_end_hold = u;
    const double fa = sim.needle(0).baseForce().dot(axis);
    if (t > 0.5 && t < T) r.push = std::max(r.push, fa);
    if (t > T + 0.2 && t < 2 * T) r.pull = std::min(r.pull, fa);
    if (t > T + 0.1 && t < 2 * T + 0.1) r.min_axial_withdrawal = std::min(r.min_axial_withdrawal, u.dot(axis));
    r.max_points = std::max(r.max_points, in->activePoints(0));
    // Action and reaction.
    const Vec3 fn = in->forceOnNeedle(0), ft = in->forceOnTissue();
    double scale = 0;
    std::map<const ContactConstraint*, std::pair<double, Vec3>> now;
    for (const auto& c : in->constraints()) {
      scale = std::max(scale, c->lambda.norm());
      if (c->kind() != ConstraintKind::Shaft) continue;
      const double lat = std::hypot(c->lambda[1], c->lambda[2]);
      r.max_cone_violation = std::max(r.max_cone_violation, std::abs(c->lambda[0]) - mu * lat * (1 + 1e-9));
      now[c.get()] = {c->s, c->lambda};
    }
    r.max_force_imbalance = std::max(r.max_force_imbalance, (fn + ft).norm() / std::max(scale, 1e-30));
    // Slip during the previous step: the needle point of a shaft point moved along the needle.
    for (const auto& [ptr, sl] : now) {
      auto it = last.find(ptr);
      if (it == last.end()) continue;
      const double slip = std::abs(sl.first - it->second.first);
      const Vec3& l = it->second.second;
      const double lat = std::hypot(l[1], l[2]);
      // Slip: the point moved along the needle by more than 5 % of the base's motion in a
      // step (2e-5 m); smaller apparent motions come from the needle's bending and
      // compression changing the closest point. On the cone: to the solver's tolerance
      // (1e-8 of the 0.05 N force scale, times 10).
      if (slip > 1e-6) {
        ++r.slips;
        if (std::abs(l[0]) >= mu * lat - 10 * 1e-8 * 0.05) ++r.slips_on_cone;
      }
    }
    last = now;
  }
  r.disp_withdrawn = sim.probeDisplacement(0);
  return r;
}
}  // namespace

// Friction 0: withdrawal leaves the tissue where it was. Friction 0.3: the tissue is dragged
// out with the needle, the holder pushes in while inserting and pulls while withdrawing; slip
// happens on the Coulomb cone and no multiplier leaves it; constraint forces on needle and
// tissue are equal and opposite.
TEST(Interaction, WithdrawalWithAndWithoutFriction) {
  const WithdrawalRun f0 = insertAndWithdraw(0.0);
  EXPECT_GT(f0.max_points, 5);
  std::printf("friction 0: max |u| %.3e, min axial while withdrawing %.3e\n", f0.max_disp, f0.min_axial_withdrawal);
  EXPECT_GT(f0.max_disp, 1e-7);
  EXPECT_LT(f0.disp_withdrawn.norm(), 1e-3 * f0.max_disp);
  EXPECT_LT(f0.max_force_imbalance, 1e-12);

  // Without friction the tissue only rebounds elastically past its rest position when the
  // needle's push stops (a few percent); with friction it is dragged out (below).
  EXPECT_GT(f0.min_axial_withdrawal, -0.2 * f0.max_disp);

  const WithdrawalRun f3 = insertAndWithdraw(0.3);
  EXPECT_GT(f3.push, 0);  // the holder pushes while inserting ...
  EXPECT_LT(f3.pull, 0);  // ... and pulls against friction while withdrawing
  // The tissue is dragged out with the needle during withdrawal, then relaxes once it is out.
  EXPECT_LT(f3.min_axial_withdrawal, -0.5 * f3.disp_end_hold.dot(Vec3(std::cos(0.0872665), std::sin(0.0872665), 0)));
  EXPECT_LT(f3.disp_withdrawn.norm(), 1e-3 * f3.max_disp);
  std::printf("friction 0.3: max |u| %.3e, end of hold %.3e, min axial while withdrawing %.3e, push %.3e, pull %.3e, slips %d\n",
              f3.max_disp, f3.disp_end_hold.norm(), f3.min_axial_withdrawal, f3.push, f3.pull, f3.slips);
  EXPECT_LE(f3.max_cone_violation, 1e-15);
  EXPECT_GT(f3.slips, 10);
  EXPECT_EQ(f3.slips_on_cone, f3.slips);
  EXPECT_LT(f3.max_force_imbalance, 1e-12);
}

// The paper's observation: probe displacements converge with mesh refinement. A shorter
// insertion (5 mm past the surface, dt = 5 ms) keeps the 32x16x16 run short. Compared: the
// radial probes 1A..1E (1.5 to 7.5 mm off the path). Probes 1..7 sit on the path itself, on
// the line of constraint point forces, where the exact field is singular and the FE values
// near the tip need not converge pointwise (they grow with refinement, as the paper notes).
TEST(Interaction, ProbeDisplacementsConvergeWithMeshRefinement) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "three insertions up to 32x16x16 (2 min under ASan): the shorter insertions here run the same path";
#endif
  std::vector<std::vector<Vec3>> result;
  for (const char* cells : {"[8,4,4]", "[16,8,8]", "[32,16,16]"}) {
    Simulation sim(phantom({std::string("tissue.grid.cells=") + cells, "time.dt=0.005", "time.duration=0.8",
                            "needle.motion=[{t: 0, advance: 0}, {t: 0.8, advance: 0.008}]"}));
    for (long k = 0; k < sim.scene().numSteps(); ++k) sim.step();
    EXPECT_EQ(sim.interaction()->state(0), InsertionState::Inserted) << cells;
    std::vector<Vec3> u;
    for (int i = 0; i < sim.numProbes(); ++i)
      if (sim.probeName(i).size() == 3) u.push_back(sim.probeDisplacement(i));  // p1A ... p1E
    result.push_back(u);
  }
  auto diff = [&](int a, int b) {
    double d = 0;
    for (size_t i = 0; i < result[a].size(); ++i) d += (result[a][i] - result[b][i]).squaredNorm();
    return std::sqrt(d);
  };
  const double d1 = diff(0, 1), d2 = diff(1, 2);
  EXPECT_GT(d1, 0);
  EXPECT_LT(d2, d1) << "8->16: " << d1 << ", 16->32: " << d2;
}

// Cannula and electrode (the DBS protocol on the phantom): the electrode rides inside the
// cannula without touching the tissue; when the cannula is withdrawn the shaft points pass
// to the electrode, whose tip is tied where it comes out; the electrode stays in place.
TEST(Interaction, ShaftPointsPassFromCannulaToElectrode) {
  Simulation sim(loadScene(std::string(NEEDLE_SIM_SOURCE_DIR) + "/config/scenes/phantom_cannula_electrode.yaml"));
  ASSERT_EQ(sim.numNeedles(), 2);
  const auto* in = sim.interaction();
  int max_cannula = 0;
  for (long k = 0; k < sim.scene().numSteps(); ++k) {
    sim.step();
    const double t = sim.time();
    if (t < 1.2) {
      EXPECT_EQ(in->activePoints(1), 0) << "t = " << t;  // sheathed: no contact of its own
      max_cannula = std::max(max_cannula, in->activePoints(0));
    }
  }
  EXPECT_GE(max_cannula, 7);  // 8 mm of cut path, a point per mm
  EXPECT_EQ(in->state(0), InsertionState::Out);
  EXPECT_EQ(in->activePoints(0), 0);
  EXPECT_EQ(in->state(1), InsertionState::Inserted);
  EXPECT_GE(in->activePoints(1), max_cannula);  // the shaft points plus the electrode's tip
  int tips = 0;
  for (const auto& c : in->constraints()) tips += c->needle == 1 && c->kind() == ConstraintKind::Tip;
  EXPECT_EQ(tips, 1);
  // The electrode stays where it was put: 8 mm deep (the commanded 11 mm from 3 mm outside).
  EXPECT_NEAR(sim.needle(1).tipPosition().x(), 0.008, 1e-5);
}
