// Reading scene files: the YAML's structure (sections, lists, alternatives such as a box or a
// surface) is read here; every value key is declared once with its settings struct and read
// through those declarations (scene/parameter_reader.hpp); the ranges and the rules that tie
// keys together are checked by checkScene (scene_check.hpp), the same check a scene built in
// code gets.
#include "needle_sim/scene/scene_loader.hpp"

#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <fstream>
#include <limits>
#include <sstream>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/parameter_reader.hpp"
#include "needle_sim/scene/scene_check.hpp"
#include "needle_sim/scene/scene_overrides.hpp"
#include "needle_sim/scene/yaml_reader.hpp"

namespace needle_sim {

long Scene::numSteps() const { return static_cast<long>(std::llround(std::ceil(duration / dt - 1e-9))); }

namespace {

void readTissue(const SceneReader& r, const YAML::Node& n, Scene& s) {
  readParameters(r, n, "tissue", TissueParameters::parameters(), s.tissue,
                 {"geometry", "grid", "dirichlet", "tractions"});
  auto& T = s.tissue;
  // geometry: exactly one of box / block / surface
  const auto g = r.child(n, "tissue", "geometry", true);
  r.checkKeys(g, "tissue.geometry", {"box", "block", "surface", "scale", "transform"});
  const int kinds = (g["box"] ? 1 : 0) + (g["block"] ? 1 : 0) + (g["surface"] ? 1 : 0);
  if (kinds > 1) r.fail("tissue.geometry", "give one of 'box', 'block' or 'surface', not several");
  if (!g["surface"] && (g["scale"] || g["transform"]))
    r.fail("tissue.geometry", "'scale' and 'transform' apply to a 'surface' only");
  if (g["box"]) {
    T.geometry.kind = TissueGeometry::Kind::Box;
    T.geometry.box = readBox(r, g["box"], "tissue.geometry.box");
  } else if (g["block"]) {
    T.geometry.kind = TissueGeometry::Kind::Block;
    const auto b = g["block"];
    r.checkKeys(b, "tissue.geometry.block", {"corners"});
    const auto c = r.child(b, "tissue.geometry.block", "corners", true);
    if (!c.IsSequence() || c.size() != 8)
      r.fail("tissue.geometry.block.corners", "must be a list of 8 points (VTK hexahedron order)");
    for (int a = 0; a < 8; ++a)
      T.geometry.corners[a] = r.vec3(c[a], "tissue.geometry.block.corners[" + std::to_string(a) + "]");
  } else if (g["surface"]) {
    T.geometry.kind = TissueGeometry::Kind::Surface;
    T.geometry.transform = readTransform(r, g, "tissue.geometry");
    T.geometry.surface_file = resolvePath(r, r.string(g["surface"], "tissue.geometry.surface"));
    T.geometry.surface = readSurfaceFile(r, g["surface"], "tissue.geometry.surface", T.geometry.transform);
  } else {
    r.fail("tissue.geometry", "missing 'box', 'block' or 'surface'");
  }
  // grid: cells over the box or block; over a surface, cells or cell_size and the immersed
  // grid's settings
  const bool immersed = T.geometry.kind == TissueGeometry::Kind::Surface;
  const auto grid = r.child(n, "tissue", "grid", true);
  if (immersed) {
    readParameters(r, grid, "tissue.grid", ImmersedGridSettings::parameters(), T.geometry.grid, {"cells"});
    if (grid["cells"] && grid["cell_size"]) r.fail("tissue.grid", "give either 'cells' or 'cell_size', not both");
    if (!grid["cells"] && !grid["cell_size"]) r.fail("tissue.grid", "missing 'cells' (or 'cell_size')");
  } else {
    r.checkKeys(grid, "tissue.grid", {"cells"});
  }
  if (grid["cells"]) {
    const auto cells = grid["cells"];
    if (!cells.IsSequence() || cells.size() != 3) r.fail("tissue.grid.cells", "must be a list of 3 integers [nx, ny, nz]");
    for (int d = 0; d < 3; ++d) {
      const long long v = r.integer(cells[d], "tissue.grid.cells[" + std::to_string(d) + "]");
      if (v < 1) r.fail("tissue.grid.cells", "every cell count must be >= 1, got " + std::to_string(v));
      if (v > 100000) r.fail("tissue.grid.cells", "cell count " + std::to_string(v) + " is too large");
      T.cells[d] = static_cast<int>(v);
    }
    if (immersed) T.geometry.grid.cells = T.cells;
  } else if (!immersed) {
    r.fail("tissue.grid.cells", "missing required key");
  }
  if (immersed) {
    ImmersedGridSettings::parameters().validate(T.geometry.grid, "tissue.grid", r.file());  // before the layout uses them
    Vec3 origin, h;
    ImmersedGrid::layout(T.geometry.surface->boundsMin(), T.geometry.surface->boundsMax(), T.geometry.grid, T.cells,
                         origin, h);
  }
  if (auto d = r.child(n, "tissue", "dirichlet", false)) {
    if (!d.IsSequence()) r.fail("tissue.dirichlet", "must be a list of {region, displacement}");
    for (size_t i = 0; i < d.size(); ++i) {
      const std::string p = "tissue.dirichlet[" + std::to_string(i) + "]";
      r.checkKeys(d[i], p, {"region", "displacement", "components"});
      DirichletCondition dc;
      dc.region = readRegion(r, r.child(d[i], p, "region", true), p + ".region", &s);
      if (auto u = r.child(d[i], p, "displacement", false)) dc.displacement = r.vec3(u, p + ".displacement");
      if (auto c = r.child(d[i], p, "components", false)) {
        if (!c.IsSequence() || c.size() == 0 || c.size() > 3)
          r.fail(p + ".components", "must be a non-empty list of 'x', 'y', 'z'");
        dc.components = {false, false, false};
        for (size_t k = 0; k < c.size(); ++k) {
          const std::string v = r.string(c[k], p + ".components");
          if (v != "x" && v != "y" && v != "z") r.fail(p + ".components", "entries must be 'x', 'y' or 'z', got '" + v + "'");
          bool& flag = dc.components[v[0] - 'x'];
          if (flag) r.fail(p + ".components", "'" + v + "' listed twice");
          flag = true;
        }
      }
      T.dirichlet.push_back(dc);
    }
  }
  if (auto tr = r.child(n, "tissue", "tractions", false)) {
    if (!tr.IsSequence()) r.fail("tissue.tractions", "must be a list of {region, traction}");
    for (size_t i = 0; i < tr.size(); ++i) {
      const std::string p = "tissue.tractions[" + std::to_string(i) + "]";
      r.checkKeys(tr[i], p, {"region", "traction"});
      TractionLoad tl;
      tl.region = readRegion(r, r.child(tr[i], p, "region", true), p + ".region", &s);
      tl.traction = r.vec3(r.child(tr[i], p, "traction", true), p + ".traction");
      T.tractions.push_back(tl);
    }
  }
}

NeedleScene readNeedle(const SceneReader& r, const YAML::Node& n, const std::string& p) {
  NeedleScene s;
  s.key = p;
  readParameters(r, n, p, NeedleParameters::parameters(), s, {"base.direction", "motion", "bevel"});
  s.base_direction = unitVector(r, r.child(n[std::string("base")], p + ".base", "direction", true), p + ".base.direction");
  if (auto b = r.child(n, p, "bevel", false)) {
    s.bevel.enabled = true;
    readParameters(r, b, p + ".bevel", BevelParameters::parameters(), s.bevel);
    // Not given: the wedge model's, once the friction is known (the loader's end).
    if (!b["lateral_ratio"]) s.bevel.lateral_ratio = std::numeric_limits<double>::quiet_NaN();
  }
  if (auto m = r.child(n, p, "motion", false)) {
    if (!m.IsSequence()) r.fail(p + ".motion", "must be a list of {t, advance} or {t, position, direction}");
    for (size_t i = 0; i < m.size(); ++i) {
      const std::string q = p + ".motion[" + std::to_string(i) + "]";
      r.checkKeys(m[i], q, {"t", "advance", "position", "direction", "roll", "spin"});
      NeedleMotionKey k;
      k.t = r.number(r.child(m[i], q, "t", true), q + ".t");
      const bool adv = static_cast<bool>(m[i]["advance"]);
      const bool pose = m[i]["position"] || m[i]["direction"];
      if (adv == pose) r.fail(q, "give either 'advance' or 'position' and 'direction'");
      if (adv) {
        const double a = r.number(m[i]["advance"], q + ".advance");
        k.position = s.base_position + a * s.base_direction;
        k.direction = s.base_direction;
      } else {
        k.position = r.vec3(r.child(m[i], q, "position", true), q + ".position");
        k.direction = unitVector(r, r.child(m[i], q, "direction", true), q + ".direction");
      }
      k.roll = s.base_roll;
      if (auto v = r.child(m[i], q, "roll", false)) k.roll = r.number(v, q + ".roll");
      if (auto sp = r.child(m[i], q, "spin", false)) {
        // Duty-cycled spinning until the next key (needle/duty_cycled_spin.hpp).
        r.checkKeys(sp, q + ".spin", {"rate", "duty"});
        k.spin_rate = r.number(r.child(sp, q + ".spin", "rate", true), q + ".spin.rate");
        k.spin_duty = r.number(r.child(sp, q + ".spin", "duty", true), q + ".spin.duty");
      }
      s.motion.push_back(k);
    }
  }
  return s;
}

void readNeedles(const SceneReader& r, const YAML::Node& root, Scene& s) {
  if (root["needle"] && root["needles"]) r.fail("needles", "give either 'needle' or 'needles', not both");
  if (auto n = r.child(root, "", "needle", false)) s.needles.push_back(readNeedle(r, n, "needle"));
  if (auto list = r.child(root, "", "needles", false)) {
    if (!list.IsSequence() || list.size() == 0) r.fail("needles", "must be a non-empty list of needles");
    for (size_t i = 0; i < list.size(); ++i) {
      const std::string p = "needles[" + std::to_string(i) + "]";
      if (!list[i].IsMap() || !list[i]["name"]) r.fail(p + ".name", "missing required key (several needles need names)");
      s.needles.push_back(readNeedle(r, list[i], p));
    }
  }
}

void readInteraction(const SceneReader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "interaction";
  InteractionSettings is;
  readParameters(r, n, p, InteractionSettings::parameters(), is, {"lateral_stiffness"});
  using Mode = InteractionSettings::LateralStiffness;
  if (auto v = r.child(n, p, "lateral_stiffness", false)) {
    if (v.IsScalar() && v.Scalar() == "auto") {
      is.lateral_mode = Mode::Auto;
    } else if (v.IsScalar() && v.Scalar() == "rigid") {
      is.lateral_mode = Mode::Rigid;
    } else {
      is.lateral_stiffness = r.number(v, p + ".lateral_stiffness");
      is.lateral_mode = Mode::Value;
    }
  } else {
    // A tip load bends a bevel needle over a length the interface sets (doc/method.md "Bevel
    // tip"); rigid ties would let the shaft points' spacing set it.
    for (const auto& nd : s.needles)
      if (nd.bevel.enabled) is.lateral_mode = Mode::Auto;
  }
  s.interaction = is;
}

void readAdaptivity(const SceneReader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "adaptivity";
  if (!n.IsMap()) r.fail(p, "must be a map {estimator, marking, theta, max_level, ...}");
  if (auto c = n["coarsen"]; c && !c.IsMap()) r.fail(p + ".coarsen", "must be a map {enabled, theta_coarsen, after}");
  AdaptivitySettings a;
  readParameters(r, n, p, AdaptivitySettings::parameters(), a, {"goal.targets"});
  if (auto g = r.child(n, p, "goal", false)) {
    const std::string q = p + ".goal";
    if (a.estimator != AdaptivitySettings::Estimator::Goal) r.fail(q, "needs estimator: goal");
    const auto t = r.child(g, q, "targets", true);
    if (!t.IsSequence() || t.size() == 0) r.fail(q + ".targets", "must be a non-empty list of target names");
    for (size_t i = 0; i < t.size(); ++i) a.goal_targets.push_back(r.string(t[i], q + ".targets[" + std::to_string(i) + "]"));
    if (!g["tolerance"]) r.fail(q + ".tolerance", "missing required key");
  } else if (a.estimator == AdaptivitySettings::Estimator::Goal) {
    r.fail(p + ".goal", "missing: estimator goal needs goal: {targets: [names], tolerance: metres}");
  }
  s.adaptivity = a;
}

void readProbes(const SceneReader& r, const YAML::Node& n, Scene& s) {
  if (!n.IsSequence()) r.fail("probes", "must be a list of {name, point}");
  for (size_t i = 0; i < n.size(); ++i) {
    const std::string p = "probes[" + std::to_string(i) + "]";
    r.checkKeys(n[i], p, {"name", "point"});
    ProbeScene pr;
    pr.name = r.string(r.child(n[i], p, "name", true), p + ".name");
    pr.point = r.vec3(r.child(n[i], p, "point", true), p + ".point");
    s.probes.push_back(pr);
  }
}

void readTargets(const SceneReader& r, const YAML::Node& n, Scene& s) {
  if (!n.IsSequence()) r.fail("targets", "must be a list of {name, point} or {name, surface}");
  for (size_t i = 0; i < n.size(); ++i) {
    const std::string p = "targets[" + std::to_string(i) + "]";
    r.checkKeys(n[i], p, {"name", "point", "surface", "scale", "transform", "radius"});
    TargetScene t;
    if (auto v = r.child(n[i], p, "radius", false)) {
      t.radius = r.number(v, p + ".radius");  // (absent: -1, the default radius)
      if (!(t.radius >= 0)) r.fail(p + ".radius", "must be >= 0 (0: the point itself), got " + SceneReader::fmt(t.radius));
    }
    t.key = p;
    t.name = r.string(r.child(n[i], p, "name", true), p + ".name");
    if (n[i]["point"] && n[i]["surface"]) r.fail(p, "give either 'point' or 'surface', not both");
    if (n[i]["point"]) {
      if (n[i]["scale"] || n[i]["transform"]) r.fail(p, "'scale'/'transform' apply to a 'surface' only");
      t.point = r.vec3(n[i]["point"], p + ".point");
    } else if (n[i]["surface"]) {
      // A target surface is in the organ's file frame unless it says otherwise.
      const SurfaceTransform t0 = readTransform(r, n[i], p, s.tissue.geometry.transform);
      t.surface = readSurfaceFile(r, n[i]["surface"], p + ".surface", t0);
      t.point = t.surface->centroid();
    } else {
      r.fail(p, "missing 'point' (or 'surface')");
    }
    s.targets.push_back(t);
  }
}

void readBrainShift(const SceneReader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "brain_shift";
  BrainShiftSettings b;
  readParameters(r, n, p, BrainShiftSettings::parameters(), b,
                 {"csf_level", "skull.surface", "skull.scale", "skull.transform"});
  if (auto v = r.child(n, p, "csf_level", false)) {
    if (v.IsScalar() && v.Scalar() == "all") {
      b.all = true;
    } else {
      r.checkKeys(v, p + ".csf_level", {"point"});
      b.all = false;
      b.csf_point = r.vec3(r.child(v, p + ".csf_level", "point", true), p + ".csf_level.point");
    }
  }
  if (auto sk = r.child(n, p, "skull", false)) {
    const std::string q = p + ".skull";
    if (sk["gap"] && sk["surface"]) r.fail(q, "give either 'gap' or 'surface', not both");
    if (sk["surface"]) b.skull = readSurfaceFile(r, sk["surface"], q + ".surface", readTransform(r, sk, q, s.tissue.geometry.transform));
  }
  // The target of the shift defaults to the first (checkScene refuses a shift target where
  // the scene has none).
  if ((b.target_shift || b.replan) && b.target.empty() && !s.targets.empty()) b.target = s.targets.front().name;
  s.brain_shift = b;
}

Scene build(YAML::Node root, const std::string& file, const std::vector<std::string>& overrides) {
  SceneReader r(file);
  if (!root.IsMap()) r.fail("", std::string("scene must be a YAML map at the top level, got ") + typeName(root));
  root = resolveExtends(root, file);
  for (const auto& o : overrides) applyOverride(root, o, file);
  r.checkKeys(root, "", {"name", "description", "time", "solver", "tissue", "needle", "needles", "interaction", "adaptivity",
                        "probes", "targets", "brain_shift"});
  Scene s;
  s.file = file;
  if (auto v = r.child(root, "", "name", false)) s.name = r.string(v, "name");
  if (s.name.empty()) {
    std::string stem = file.substr(file.find_last_of('/') + 1);
    s.name = stem.substr(0, stem.find_last_of('.'));
  }
  if (auto v = r.child(root, "", "description", false)) s.description = r.string(v, "description");
  readParameters(r, r.child(root, "", "time", true), "time", Scene::timeParameters(), s);
  if (auto v = r.child(root, "", "solver", false)) readParameters(r, v, "solver", SolverSettings::parameters(), s.solver);
  if (auto t = r.child(root, "", "tissue", false)) readTissue(r, t, s);
  else s.has_tissue = false;
  readNeedles(r, root, s);
  if (!s.has_tissue && s.needles.empty()) r.fail("tissue", "missing: a scene needs a tissue, a needle, or both");
  if (auto v = r.child(root, "", "interaction", false)) readInteraction(r, v, s);
  if (auto v = r.child(root, "", "adaptivity", false)) readAdaptivity(r, v, s);
  if (auto v = r.child(root, "", "probes", false)) {
    if (!s.has_tissue) r.fail("probes", "probes are tissue points, but the scene has no tissue");
    readProbes(r, v, s);
  }
  if (auto v = r.child(root, "", "targets", false)) {
    if (!s.has_tissue) r.fail("targets", "targets are tissue points, but the scene has no tissue");
    readTargets(r, v, s);
  }
  if (auto v = r.child(root, "", "brain_shift", false)) {
    if (!s.has_tissue) r.fail("brain_shift", "needs a tissue (the scene has none)");
    readBrainShift(r, v, s);
  }
  // A bevel's lateral ratio, where not given: the wedge model's with the shaft's friction
  // (without an interaction checkScene refuses the bevel).
  for (auto& nd : s.needles)
    if (nd.bevel.enabled && std::isnan(nd.bevel.lateral_ratio) && s.interaction)
      nd.bevel.lateral_ratio = bevelLateralRatio(nd.bevel.angle, s.interaction->friction);
  checkScene(s);
  return s;
}

}  // namespace

Scene parseScene(const std::string& text, const std::string& file, const std::vector<std::string>& overrides) {
  YAML::Node root;
  try {
    root = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    throw InputError(file, "", "not valid YAML: " + e.msg + " (line " + std::to_string(e.mark.line + 1) + ")");
  }
  try {
    return build(root, file, overrides);
  } catch (const YAML::Exception& e) {
    // Every read is checked; this is the safety net for a conversion the checks missed.
    throw InputError(file, "", "unreadable value: " + e.msg + " (line " + std::to_string(e.mark.line + 1) + ")");
  }
}

Scene loadScene(const std::string& path, const std::vector<std::string>& overrides) {
  std::ifstream in(path);
  if (!in) throw InputError(path, "", "cannot open scene file");
  std::stringstream ss;
  ss << in.rdbuf();
  return parseScene(ss.str(), path, overrides);
}

}  // namespace needle_sim
