#include "needle_sim/scene/scene_check.hpp"

#include <cmath>
#include <cstdio>
#include <regex>
#include <set>

#include "needle_sim/scene/resource_check.hpp"
#include "needle_sim/scene/yaml_reader.hpp"

namespace needle_sim {

namespace {

const std::regex& identifier() {
  static const std::regex ident("[A-Za-z0-9_]+");
  return ident;
}

void checkNeedle(const SceneReader& r, const Scene& s, const NeedleScene& nd) {
  const std::string& p = nd.key;
  if (!std::regex_match(nd.name, identifier()))
    r.fail(p + ".name", "must be letters, digits and '_' only (it names CSV columns), got '" + nd.name + "'");
  NeedleParameters::parameters().validate(nd, p, s.file);
  if (nd.inner_radius >= nd.radius)
    r.fail(p + ".inner_radius", "must be smaller than radius (" + SceneReader::fmt(nd.inner_radius) +
                                    " >= " + SceneReader::fmt(nd.radius) + ")");
  for (size_t i = 0; i < nd.motion.size(); ++i) {
    const NeedleMotionKey& k = nd.motion[i];
    const std::string q = p + ".motion[" + std::to_string(i) + "]";
    if (!(k.t >= 0)) r.fail(q + ".t", "must be >= 0");
    if (i > 0 && !(k.t > nd.motion[i - 1].t))
      r.fail(q + ".t", "times must increase strictly (" + SceneReader::fmt(k.t) + " after " +
                           SceneReader::fmt(nd.motion[i - 1].t) + ")");
    if (k.spin_rate != 0 || k.spin_duty != 0) {
      if (!(k.spin_duty >= 0 && k.spin_duty <= 1))
        r.fail(q + ".spin.duty", "must be in [0, 1] (the fraction of the time spent spinning), got " +
                                     SceneReader::fmt(k.spin_duty));
      if (!(k.spin_rate > 0)) r.fail(q + ".spin.rate", "must be > 0 [rad/s], got " + SceneReader::fmt(k.spin_rate));
      if (i + 1 == nd.motion.size()) r.fail(q + ".spin", "spins until the next key, but this is the last key");
    }
  }
  if (nd.bevel.enabled) {
    if (!s.interaction) r.fail(p + ".bevel", "a bevel acts while the tip cuts: the scene needs an 'interaction' section");
    BevelParameters::parameters().validate(nd.bevel, p + ".bevel", s.file);
  }
}

void checkInteraction(const SceneReader& r, const Scene& s) {
  const std::string p = "interaction";
  const InteractionSettings& is = *s.interaction;
  InteractionSettings::parameters().validate(is, p, s.file);
  if (is.lateral_mode == InteractionSettings::LateralStiffness::Value &&
      !(is.lateral_stiffness > 0 && std::isfinite(is.lateral_stiffness)))
    r.fail(p + ".lateral_stiffness",
           "must be 'auto', 'rigid' or a stiffness > 0 [Pa], got " + SceneReader::fmt(is.lateral_stiffness));
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (s.needles.empty()) r.fail(p, "needs a needle (the scene has none)");
  if (s.solver.mode != SolverSettings::Mode::Dynamic) r.fail(p, "needs solver.mode: dynamic");
}

void checkAdaptivity(const SceneReader& r, const Scene& s) {
  const std::string p = "adaptivity";
  const AdaptivitySettings& a = *s.adaptivity;
  AdaptivitySettings::parameters().validate(a, p, s.file);
  const bool goal = a.estimator == AdaptivitySettings::Estimator::Goal;
  if (goal && a.goal_targets.empty()) r.fail(p + ".goal.targets", "must be a non-empty list of target names");
  if (goal && !(a.goal_tolerance > 0)) r.fail(p + ".goal.tolerance", "must be > 0 [m] with estimator: goal");
  if (!goal && !a.goal_targets.empty()) r.fail(p + ".goal", "needs estimator: goal");
  if (a.estimate_delay > a.rebuild_delay)
    r.fail(p + ".estimate_delay", "must be in [0, rebuild_delay = " + SceneReader::fmt(a.rebuild_delay) +
                                      "] s (a change is switched to after its decision), got " +
                                      SceneReader::fmt(a.estimate_delay));
  // A merged parent's error is about twice its children's combined (linear elements, h
  // doubled): below theta / 2 it cannot be marked again at once, so nothing flickers.
  if (a.coarsen && a.marking == AdaptivitySettings::Marking::Max && !(a.theta_coarsen < 0.5 * a.theta))
    r.fail(p + ".coarsen.theta_coarsen", "must be < theta / 2 = " + SceneReader::fmt(0.5 * a.theta) +
                                             " (hysteresis: a merged element would be refined again at once), got " +
                                             SceneReader::fmt(a.theta_coarsen));
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (a.max_dofs == 0 && s.tissue.cells.cast<double>().prod() * std::pow(8.0, a.max_level) > 5e7)
    r.fail(p + ".max_level", "a fully refined grid of " + std::to_string(s.tissue.cells.prod()) + " cells at level " +
                                 std::to_string(a.max_level) +
                                 " would exceed 5e7 elements; lower max_level, set a coarser grid or a max_dofs budget");
}

// Probe and target names name CSV columns and tf frames.
void checkNames(const SceneReader& r, const std::string& list, const std::vector<std::string>& names,
                const char* what) {
  std::set<std::string> seen;
  for (size_t i = 0; i < names.size(); ++i) {
    const std::string p = list + "[" + std::to_string(i) + "].name";
    if (!std::regex_match(names[i], identifier()))
      r.fail(p, "must be letters, digits and '_' only (it names CSV columns and frames), got '" + names[i] + "'");
    if (!seen.insert(names[i]).second) r.fail(p, std::string("duplicate ") + what + " name '" + names[i] + "'");
  }
}

bool hasTarget(const Scene& s, const std::string& name) {
  for (const auto& t : s.targets)
    if (t.name == name) return true;
  return false;
}

void checkBrainShift(const SceneReader& r, const Scene& s) {
  const std::string p = "brain_shift";
  const BrainShiftSettings& b = *s.brain_shift;
  if (!(b.gravity.norm() > 0)) r.fail(p + ".gravity", "must be a non-zero vector");
  BrainShiftSettings::parameters().validate(b, p, s.file);
  if (b.replan && s.needles.empty()) r.fail(p + ".replan", "re-aims the needles: the scene has none");
  if (b.target_shift || !b.target.empty() || b.replan) {
    if (s.targets.empty())
      r.fail(p + (b.replan ? ".replan" : b.target.empty() ? ".target_shift" : ".target"), "needs a target (the scene has none)");
    if (!hasTarget(s, b.target)) r.fail(p + ".target", "no target named '" + b.target + "'");
  }
  if (s.tissue.dirichlet.empty()) r.fail("tissue.dirichlet", "brain shift needs clamped regions that hold the brain");
}

}  // namespace

void checkScene(const Scene& s) {
  const SceneReader r(s.file);
  Scene::timeParameters().validate(s, "time", s.file);
  if (s.duration / s.dt > 1e9) r.fail("time", "duration / dt exceeds 1e9 steps");
  SolverSettings::parameters().validate(s.solver, "solver", s.file);
  // The rotation part enters the Krylov operator; a direct solve uses the factor alone.
  if (s.solver.static_rotation_tangent && s.solver.linear.method == LinearSolverSettings::Method::Direct)
    r.fail("solver.static.rotation_tangent",
           "needs solver.linear.method 'pcg' (the direct method solves with the symmetric factor only)");
  if (s.has_tissue) {
    for (int d = 0; d < 3; ++d)
      if (s.tissue.cells[d] < 1 || s.tissue.cells[d] > 100000)
        r.fail("tissue.grid.cells", "cell count " + std::to_string(s.tissue.cells[d]) + " is not in [1, 100000]");
    if (s.tissue.geometry.kind == TissueGeometry::Kind::Surface) {
      ImmersedGridSettings::parameters().validate(s.tissue.geometry.grid, "tissue.grid", s.file);
      if (s.tissue.cells.cast<double>().prod() > 2e7)
        r.fail(s.tissue.geometry.grid.cells ? "tissue.grid.cells" : "tissue.grid.cell_size",
               "gives a grid of " + SceneReader::fmt(s.tissue.cells.cast<double>().prod()) +
                   " cells over the surface's box: too many");
    }
    checkSolverMemory(s.tissue.cells, s.file, "tissue.grid.cells");
    TissueParameters::parameters().validate(s.tissue, "tissue", s.file);
  }
  if (!s.has_tissue && s.needles.empty()) r.fail("tissue", "missing: a scene needs a tissue, a needle, or both");
  std::set<std::string> needle_names;
  for (const auto& nd : s.needles) {
    checkNeedle(r, s, nd);
    if (!needle_names.insert(nd.name).second) r.fail(nd.key + ".name", "duplicate needle name '" + nd.name + "'");
  }
  if (s.interaction) checkInteraction(r, s);
  if (s.adaptivity) checkAdaptivity(r, s);
  if (!s.probes.empty() && !s.has_tissue) r.fail("probes", "probes are tissue points, but the scene has no tissue");
  std::vector<std::string> names;
  for (const auto& p : s.probes) names.push_back(p.name);
  checkNames(r, "probes", names, "probe");
  if (!s.targets.empty() && !s.has_tissue) r.fail("targets", "targets are tissue points, but the scene has no tissue");
  names.clear();
  for (size_t i = 0; i < s.targets.size(); ++i) {
    if (!(s.targets[i].radius >= 0 || s.targets[i].radius == -1))  // -1: the default radius
      r.fail("targets[" + std::to_string(i) + "].radius",
             "must be >= 0 (0: the point itself), got " + SceneReader::fmt(s.targets[i].radius));
    names.push_back(s.targets[i].name);
  }
  checkNames(r, "targets", names, "target");
  if (s.brain_shift) checkBrainShift(r, s);
  // Goal-oriented adaptivity names targets: they must exist.
  if (s.adaptivity)
    for (size_t i = 0; i < s.adaptivity->goal_targets.size(); ++i)
      if (!hasTarget(s, s.adaptivity->goal_targets[i]))
        r.fail("adaptivity.goal.targets[" + std::to_string(i) + "]",
               "no target named '" + s.adaptivity->goal_targets[i] + "' in targets");
  if (s.has_tissue && s.solver.mode == SolverSettings::Mode::Static && s.tissue.dirichlet.empty())
    r.fail("tissue.dirichlet", "static mode needs Dirichlet conditions that hold the body (none given)");
}

// The incompatible modes alone keep the full volume stiffness at the Gauss points: on the
// paper's block (8x4x4, doc/verification.md "Nearly incompressible tissue") 10 % too stiff at
// nu 0.499 and 16 % at 0.4999, where incompatible_modes_bbar is within 5 %.
constexpr double kIncompatibleModesLockingPoisson = 0.499;

std::vector<std::string> sceneWarnings(const Scene& s) {
  std::vector<std::string> w;
  const LinearElasticMaterial& m = s.tissue.material;
  if (!s.has_tissue) return w;
  char nu[32];
  std::snprintf(nu, sizeof nu, "%g", m.poisson);
  const std::string where = std::string(s.file.empty() ? "scene" : s.file) + ": tissue.element: ";
  const std::string instead = "; tissue.element: incompatible_modes_bbar does not (doc/method.md \"Tissue\")";
  if (m.element == HexFormulation::Trilinear && m.poisson >= kTrilinearLockingPoisson)
    w.push_back(where + "trilinear at tissue.material.poisson " + nu +
                " locks volumetrically (too stiff: 15 % on the paper's block at 0.45, 74 % at 0.4999)" + instead);
  if (m.element == HexFormulation::IncompatibleModes && m.poisson >= kIncompatibleModesLockingPoisson)
    w.push_back(where + "incompatible_modes at tissue.material.poisson " + nu +
                " locks volumetrically (too stiff: 10 % on the paper's block at 0.499, 16 % at 0.4999)" + instead);
  return w;
}

}  // namespace needle_sim
