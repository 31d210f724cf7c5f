#include "needle_sim/scene/scene_loader.hpp"

#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <regex>
#include <set>
#include <sstream>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/resource_check.hpp"
#include "needle_sim/scene/scene_overrides.hpp"
#include "needle_sim/scene/yaml_reader.hpp"

namespace needle_sim {

long Scene::numSteps() const { return static_cast<long>(std::llround(std::ceil(duration / dt - 1e-9))); }

namespace {

void readTime(const SceneReader& r, const YAML::Node& n, Scene& s) {
  r.checkKeys(n, "time", {"dt", "duration"});
  s.dt = r.positive(n, "time", "dt");
  s.duration = r.positive(n, "time", "duration");
  if (s.duration / s.dt > 1e9) r.fail("time", "duration / dt exceeds 1e9 steps");
}

void readSolver(const SceneReader& r, const YAML::Node& n, Scene& s) {
  r.checkKeys(n, "solver", {"mode", "rayleigh", "static", "linear"});
  if (auto m = r.child(n, "solver", "mode", false)) {
    const std::string mode = r.string(m, "solver.mode");
    if (mode == "dynamic") s.solver.mode = SolverSettings::Mode::Dynamic;
    else if (mode == "static") s.solver.mode = SolverSettings::Mode::Static;
    else r.fail("solver.mode", "must be 'dynamic' or 'static', got '" + mode + "'");
  }
  if (auto ray = r.child(n, "solver", "rayleigh", false)) {
    r.checkKeys(ray, "solver.rayleigh", {"mass", "stiffness"});
    if (auto a = r.child(ray, "solver.rayleigh", "mass", false)) s.solver.rayleigh_mass = r.number(a, "solver.rayleigh.mass");
    if (auto b = r.child(ray, "solver.rayleigh", "stiffness", false))
      s.solver.rayleigh_stiffness = r.number(b, "solver.rayleigh.stiffness");
    if (s.solver.rayleigh_mass < 0) r.fail("solver.rayleigh.mass", "must be >= 0");
    if (s.solver.rayleigh_stiffness < 0) r.fail("solver.rayleigh.stiffness", "must be >= 0");
  }
  if (auto st = r.child(n, "solver", "static", false)) {
    r.checkKeys(st, "solver.static", {"tolerance", "max_iterations", "rotation_tangent"});
    if (auto rt = r.child(st, "solver.static", "rotation_tangent", false))
      s.solver.static_rotation_tangent = r.boolean(rt, "solver.static.rotation_tangent");
    if (st["tolerance"]) s.solver.static_tolerance = r.positive(st, "solver.static", "tolerance");
    if (auto it = r.child(st, "solver.static", "max_iterations", false)) {
      const long long v = r.integer(it, "solver.static.max_iterations");
      if (v < 1 || v > 100000) r.fail("solver.static.max_iterations", "must be in [1, 100000]");
      s.solver.static_max_iterations = static_cast<int>(v);
    }
  }
  if (auto li = r.child(n, "solver", "linear", false)) {
    const std::string p = "solver.linear";
    r.checkKeys(li, p, {"method", "tolerance", "max_iterations", "refresh_iterations", "refactor_every", "ordering",
                        "async", "async_lag"});
    auto& L = s.solver.linear;
    if (auto m = r.child(li, p, "method", false)) {
      const std::string v = r.string(m, p + ".method");
      if (v == "direct") L.method = LinearSolverSettings::Method::Direct;
      else if (v == "pcg") L.method = LinearSolverSettings::Method::Pcg;
      else r.fail(p + ".method", "must be 'direct' or 'pcg', got '" + v + "'");
    }
    if (li["tolerance"]) {
      L.tolerance = r.positive(li, p, "tolerance");
      if (L.tolerance >= 1) r.fail(p + ".tolerance", "must be < 1");
    }
    auto readInt = [&](const char* key, int lo, int& out) {
      if (auto v = r.child(li, p, key, false)) {
        const long long x = r.integer(v, SceneReader::join(p, key));
        if (x < lo || x > 1000000) r.fail(SceneReader::join(p, key), "must be in [" + std::to_string(lo) + ", 1000000]");
        out = static_cast<int>(x);
      }
    };
    readInt("max_iterations", 1, L.max_iterations);
    readInt("refresh_iterations", 0, L.refresh_iterations);
    readInt("refactor_every", 0, L.refactor_every);
    readInt("async_lag", 0, L.async_lag);
    if (auto v = r.child(li, p, "async", false)) L.async = r.boolean(v, p + ".async");
    if (auto o = r.child(li, p, "ordering", false)) {
      const std::string v = r.string(o, p + ".ordering");
      if (v == "auto") L.ordering = Ordering::Auto;
      else if (v == "amd") L.ordering = Ordering::Amd;
      else if (v == "metis") L.ordering = Ordering::Metis;
      else r.fail(p + ".ordering", "must be 'auto', 'amd' or 'metis', got '" + v + "'");
    }
  }
  // The rotation part enters the Krylov operator; a direct solve uses the factor alone.
  if (s.solver.static_rotation_tangent && s.solver.linear.method == LinearSolverSettings::Method::Direct)
    r.fail("solver.static.rotation_tangent", "needs solver.linear.method 'pcg' (the direct method solves with the symmetric factor only)");
}

void readTissue(const SceneReader& r, const YAML::Node& n, Scene& s) {
  r.checkKeys(n, "tissue", {"geometry", "grid", "material", "gravity", "body_force", "dirichlet", "tractions"});
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
  // grid
  const bool immersed = T.geometry.kind == TissueGeometry::Kind::Surface;
  const auto grid = r.child(n, "tissue", "grid", true);
  if (immersed) r.checkKeys(grid, "tissue.grid", {"cells", "cell_size", "refine", "min_fraction", "samples"});
  else r.checkKeys(grid, "tissue.grid", {"cells"});
  if (immersed && grid["cells"] && grid["cell_size"]) r.fail("tissue.grid", "give either 'cells' or 'cell_size', not both");
  if (immersed && !grid["cells"] && !grid["cell_size"]) r.fail("tissue.grid", "missing 'cells' (or 'cell_size')");
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
    auto& G = T.geometry.grid;
    if (grid["cell_size"]) G.cell_size = r.positive(grid, "tissue.grid", "cell_size");
    if (auto v = r.child(grid, "tissue.grid", "refine", false)) {
      const long long k = r.integer(v, "tissue.grid.refine");
      if (k < 0 || k > 6) r.fail("tissue.grid.refine", "must be in [0, 6]");
      G.refine = static_cast<int>(k);
    }
    if (auto v = r.child(grid, "tissue.grid", "min_fraction", false)) {
      G.min_fraction = r.number(v, "tissue.grid.min_fraction");
      if (!(G.min_fraction > 0 && G.min_fraction <= 1)) r.fail("tissue.grid.min_fraction", "must be in (0, 1]");
    }
    if (auto v = r.child(grid, "tissue.grid", "samples", false)) {
      const long long k = r.integer(v, "tissue.grid.samples");
      if (k < 1 || k > 64) r.fail("tissue.grid.samples", "must be in [1, 64]");
      G.samples = static_cast<int>(k);
    }
    Vec3 origin, h;
    ImmersedGrid::layout(T.geometry.surface->boundsMin(), T.geometry.surface->boundsMax(), G, T.cells, origin, h);
    if (T.cells.cast<double>().prod() > 2e7)
      r.fail(G.cells ? "tissue.grid.cells" : "tissue.grid.cell_size",
             "gives a grid of " + SceneReader::fmt(T.cells.cast<double>().prod()) + " cells over the surface's box: too many");
  }
  checkSolverMemory(T.cells, r.file(), "tissue.grid.cells");
  // material
  const auto mat = r.child(n, "tissue", "material", true);
  r.checkKeys(mat, "tissue.material", {"young", "poisson", "density"});
  T.material.young = r.positive(mat, "tissue.material", "young");
  T.material.poisson = r.number(r.child(mat, "tissue.material", "poisson", true), "tissue.material.poisson");
  if (!(T.material.poisson > -1 && T.material.poisson < 0.5))
    r.fail("tissue.material.poisson", "must be in (-1, 0.5), got " + SceneReader::fmt(T.material.poisson));
  T.material.density = r.positive(mat, "tissue.material", "density");
  if (auto v = r.child(n, "tissue", "gravity", false)) T.gravity = r.vec3(v, "tissue.gravity");
  if (auto v = r.child(n, "tissue", "body_force", false)) T.body_force = r.vec3(v, "tissue.body_force");
  if (auto d = r.child(n, "tissue", "dirichlet", false)) {
    if (!d.IsSequence()) r.fail("tissue.dirichlet", "must be a list of {region, displacement}");
    for (size_t i = 0; i < d.size(); ++i) {
      const std::string p = "tissue.dirichlet[" + std::to_string(i) + "]";
      r.checkKeys(d[i], p, {"region", "displacement", "components"});
      DirichletCondition dc;
      dc.key = p;
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
      tl.key = p;
      tl.region = readRegion(r, r.child(tr[i], p, "region", true), p + ".region", &s);
      tl.traction = r.vec3(r.child(tr[i], p, "traction", true), p + ".traction");
      T.tractions.push_back(tl);
    }
  }
}

NeedleScene readNeedle(const SceneReader& r, const YAML::Node& n, const std::string& p) {
  r.checkKeys(n, p, {"name", "length", "radius", "inner_radius", "young", "poisson", "density", "elements", "base",
                     "motion", "tip_force", "tip_moment", "gravity", "bevel"});
  static const std::regex ident("[A-Za-z0-9_]+");
  NeedleScene s;
  s.key = p;
  if (auto v = r.child(n, p, "name", false)) {
    s.name = r.string(v, p + ".name");
    if (!std::regex_match(s.name, ident))
      r.fail(p + ".name", "must be letters, digits and '_' only (it names CSV columns), got '" + s.name + "'");
  }
  s.length = r.positive(n, p, "length");
  s.radius = r.positive(n, p, "radius");
  if (auto v = r.child(n, p, "inner_radius", false)) {
    s.inner_radius = r.number(v, p + ".inner_radius");
    if (s.inner_radius < 0) r.fail(p + ".inner_radius", "must be >= 0");
    if (s.inner_radius >= s.radius)
      r.fail(p + ".inner_radius", "must be smaller than radius (" + SceneReader::fmt(s.inner_radius) +
                                      " >= " + SceneReader::fmt(s.radius) + ")");
  }
  s.young = r.positive(n, p, "young");
  s.poisson = r.number(r.child(n, p, "poisson", true), p + ".poisson");
  if (!(s.poisson > -1 && s.poisson < 0.5)) r.fail(p + ".poisson", "must be in (-1, 0.5), got " + SceneReader::fmt(s.poisson));
  s.density = r.positive(n, p, "density");
  const long long el = r.integer(r.child(n, p, "elements", true), p + ".elements");
  if (el < 1 || el > 100000) r.fail(p + ".elements", "must be in [1, 100000], got " + std::to_string(el));
  s.elements = static_cast<int>(el);
  const auto base = r.child(n, p, "base", true);
  r.checkKeys(base, p + ".base", {"position", "direction", "roll"});
  s.base_position = r.vec3(r.child(base, p + ".base", "position", true), p + ".base.position");
  s.base_direction = unitVector(r, r.child(base, p + ".base", "direction", true), p + ".base.direction");
  if (auto v = r.child(base, p + ".base", "roll", false)) s.base_roll = r.number(v, p + ".base.roll");
  if (auto v = r.child(n, p, "tip_force", false)) s.tip_force = r.vec3(v, p + ".tip_force");
  if (auto v = r.child(n, p, "tip_moment", false)) s.tip_moment = r.vec3(v, p + ".tip_moment");
  if (auto v = r.child(n, p, "gravity", false)) s.gravity = r.vec3(v, p + ".gravity");
  if (auto b = r.child(n, p, "bevel", false)) {
    const std::string q = p + ".bevel";
    r.checkKeys(b, q, {"angle", "lateral_ratio", "orientation"});
    s.bevel.enabled = true;
    s.bevel.angle = r.number(r.child(b, q, "angle", true), q + ".angle");
    if (!(s.bevel.angle > 0 && s.bevel.angle < M_PI / 2))
      r.fail(q + ".angle", "must be in (0, pi/2) radians (the face's angle to the needle axis), got " + SceneReader::fmt(s.bevel.angle));
    s.bevel.lateral_ratio = std::numeric_limits<double>::quiet_NaN();  // the wedge model's, once the friction is known
    if (auto v = r.child(b, q, "lateral_ratio", false)) {
      s.bevel.lateral_ratio = r.number(v, q + ".lateral_ratio");
      if (!(s.bevel.lateral_ratio >= 0)) r.fail(q + ".lateral_ratio", "must be >= 0, got " + SceneReader::fmt(s.bevel.lateral_ratio));
    }
    if (auto v = r.child(b, q, "orientation", false)) s.bevel.orientation = r.number(v, q + ".orientation");
  }
  if (auto m = r.child(n, p, "motion", false)) {
    if (!m.IsSequence()) r.fail(p + ".motion", "must be a list of {t, advance} or {t, position, direction}");
    for (size_t i = 0; i < m.size(); ++i) {
      const std::string q = p + ".motion[" + std::to_string(i) + "]";
      r.checkKeys(m[i], q, {"t", "advance", "position", "direction", "roll", "spin"});
      NeedleMotionKey k;
      k.t = r.number(r.child(m[i], q, "t", true), q + ".t");
      if (k.t < 0) r.fail(q + ".t", "must be >= 0");
      if (i > 0 && !(k.t > s.motion.back().t))
        r.fail(q + ".t", "times must increase strictly (" + SceneReader::fmt(k.t) + " after " + SceneReader::fmt(s.motion.back().t) + ")");
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
        if (!(k.spin_duty >= 0 && k.spin_duty <= 1))
          r.fail(q + ".spin.duty", "must be in [0, 1] (the fraction of the time spent spinning), got " + SceneReader::fmt(k.spin_duty));
        if (!(k.spin_rate > 0)) r.fail(q + ".spin.rate", "must be > 0 [rad/s], got " + SceneReader::fmt(k.spin_rate));
        if (i + 1 == m.size()) r.fail(q + ".spin", "spins until the next key, but this is the last key");
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
    std::set<std::string> names;
    for (size_t i = 0; i < list.size(); ++i) {
      const std::string p = "needles[" + std::to_string(i) + "]";
      if (!list[i].IsMap() || !list[i]["name"]) r.fail(p + ".name", "missing required key (several needles need names)");
      NeedleScene ns = readNeedle(r, list[i], p);
      if (!names.insert(ns.name).second) r.fail(p + ".name", "duplicate needle name '" + ns.name + "'");
      s.needles.push_back(ns);
    }
  }
}

void readInteraction(const SceneReader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "interaction";
  r.checkKeys(n, p, {"puncture_force", "cutting_force", "friction", "shaft_spacing", "grip_pressure", "lateral_stiffness", "solver"});
  InteractionSettings is;
  auto nonNegative = [&](const char* key) {
    const std::string k = SceneReader::join(p, key);
    const double v = r.number(r.child(n, p, key, true), k);
    if (v < 0) r.fail(k, "must be >= 0, got " + SceneReader::fmt(v));
    return v;
  };
  is.puncture_force = nonNegative("puncture_force");
  is.cutting_force = nonNegative("cutting_force");
  is.friction = nonNegative("friction");
  is.shaft_spacing = r.positive(n, p, "shaft_spacing");
  if (auto v = r.child(n, p, "grip_pressure", false)) {
    is.grip_pressure = r.number(v, p + ".grip_pressure");
    if (!(is.grip_pressure >= 0)) r.fail(p + ".grip_pressure", "must be >= 0 [Pa], got " + SceneReader::fmt(is.grip_pressure));
  }
  if (auto v = r.child(n, p, "lateral_stiffness", false)) {
    const std::string k = p + ".lateral_stiffness";
    using Mode = InteractionSettings::LateralStiffness;
    if (v.IsScalar() && v.Scalar() == "auto") {
      is.lateral_mode = Mode::Auto;
    } else if (v.IsScalar() && v.Scalar() == "rigid") {
      is.lateral_mode = Mode::Rigid;
    } else {
      is.lateral_stiffness = r.number(v, k);
      if (!(is.lateral_stiffness > 0 && std::isfinite(is.lateral_stiffness)))
        r.fail(k, "must be 'auto', 'rigid' or a stiffness > 0 [Pa], got " + SceneReader::fmt(is.lateral_stiffness));
      is.lateral_mode = Mode::Value;
    }
  } else {
    // A tip load bends a bevel needle over a length the interface sets (doc/method.md "Bevel
    // tip"); rigid ties would let the shaft points' spacing set it.
    for (const auto& nd : s.needles)
      if (nd.bevel.enabled) is.lateral_mode = InteractionSettings::LateralStiffness::Auto;
  }
  if (auto sv = r.child(n, p, "solver", false)) {
    r.checkKeys(sv, p + ".solver", {"method", "tolerance", "max_iterations"});
    if (auto m = r.child(sv, p + ".solver", "method", false)) {
      const std::string v = r.string(m, p + ".solver.method");
      if (v == "block") is.solver = ConstraintSolver::BlockActiveSet;
      else if (v == "gauss_seidel") is.solver = ConstraintSolver::GaussSeidel;
      else r.fail(p + ".solver.method", "must be 'block' or 'gauss_seidel', got '" + v + "'");
    }
    if (sv["tolerance"]) is.tolerance = r.positive(sv, p + ".solver", "tolerance");
    if (auto it = r.child(sv, p + ".solver", "max_iterations", false)) {
      const long long v = r.integer(it, p + ".solver.max_iterations");
      if (v < 1 || v > 1000000) r.fail(p + ".solver.max_iterations", "must be in [1, 1000000]");
      is.max_iterations = static_cast<int>(v);
    }
  }
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (s.needles.empty()) r.fail(p, "needs a needle (the scene has none)");
  if (s.solver.mode != SolverSettings::Mode::Dynamic) r.fail(p, "needs solver.mode: dynamic");
  s.interaction = is;
}

void readAdaptivity(const SceneReader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "adaptivity";
  if (!n.IsMap()) r.fail(p, "must be a map {estimator, marking, theta, max_level, ...}");
  r.checkKeys(n, p, {"estimator", "goal", "marking", "theta", "max_level", "max_dofs", "tolerance", "every_steps",
                     "coarsen", "rebuild_delay", "estimate_delay"});
  AdaptivitySettings a;
  if (auto v = r.child(n, p, "estimator", false)) {
    const std::string e = r.string(v, p + ".estimator");
    if (e == "goal") a.estimator = AdaptivitySettings::Estimator::Goal;
    else if (e != "spr") r.fail(p + ".estimator", "unknown estimator '" + e + "' (available: spr, goal)");
  }
  if (auto g = r.child(n, p, "goal", false)) {
    const std::string q = p + ".goal";
    if (a.estimator != AdaptivitySettings::Estimator::Goal) r.fail(q, "needs estimator: goal");
    r.checkKeys(g, q, {"targets", "tolerance"});
    const auto t = r.child(g, q, "targets", true);
    if (!t.IsSequence() || t.size() == 0) r.fail(q + ".targets", "must be a non-empty list of target names");
    for (size_t i = 0; i < t.size(); ++i) a.goal_targets.push_back(r.string(t[i], q + ".targets[" + std::to_string(i) + "]"));
    a.goal_tolerance = r.positive(g, q, "tolerance");
  } else if (a.estimator == AdaptivitySettings::Estimator::Goal) {
    r.fail(p + ".goal", "missing: estimator goal needs goal: {targets: [names], tolerance: metres}");
  }
  if (auto v = r.child(n, p, "marking", false)) {
    const std::string m = r.string(v, p + ".marking");
    if (m == "max") a.marking = AdaptivitySettings::Marking::Max;
    else if (m == "bulk") a.marking = AdaptivitySettings::Marking::Bulk;
    else r.fail(p + ".marking", "must be max or bulk, got '" + m + "'");
  }
  a.theta = r.number(r.child(n, p, "theta", true), p + ".theta");
  if (!(a.theta > 0 && a.theta <= 1)) r.fail(p + ".theta", "must be in (0, 1], got " + SceneReader::fmt(a.theta));
  auto integerIn = [&](const YAML::Node& parent, const std::string& path, const char* key, long long lo, long long hi,
                       int& out) {
    if (auto v = r.child(parent, path, key, false)) {
      const std::string k = SceneReader::join(path, key);
      const long long x = r.integer(v, k);
      if (x < lo || x > hi)
        r.fail(k, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got " + std::to_string(x));
      out = static_cast<int>(x);
    }
  };
  integerIn(n, p, "max_level", 0, 6, a.max_level);
  integerIn(n, p, "max_dofs", 0, 100000000, a.max_dofs);
  integerIn(n, p, "every_steps", 1, 1000000000, a.every_steps);
  if (auto v = r.child(n, p, "rebuild_delay", false)) {
    a.rebuild_delay = r.number(v, p + ".rebuild_delay");
    if (!(a.rebuild_delay >= 0 && a.rebuild_delay <= 10))
      r.fail(p + ".rebuild_delay", "must be in [0, 10] s, got " + SceneReader::fmt(a.rebuild_delay));
  }
  if (auto v = r.child(n, p, "estimate_delay", false)) {
    a.estimate_delay = r.number(v, p + ".estimate_delay");
    if (!(a.estimate_delay >= 0 && a.estimate_delay <= a.rebuild_delay))
      r.fail(p + ".estimate_delay", "must be in [0, rebuild_delay = " + SceneReader::fmt(a.rebuild_delay) +
                                        "] s (a change is switched to after its decision), got " +
                                        SceneReader::fmt(a.estimate_delay));
    if (a.estimate_delay > 0 && a.estimator == AdaptivitySettings::Estimator::Goal)
      r.fail(p + ".estimate_delay", "must be 0 with estimator: goal (its dual solves use the tissue's factor, "
                                    "on the stepping thread)");
  }
  if (auto v = r.child(n, p, "tolerance", false)) {
    a.tolerance = r.number(v, p + ".tolerance");
    if (a.tolerance < 0) r.fail(p + ".tolerance", "must be >= 0, got " + SceneReader::fmt(a.tolerance));
  }
  if (auto c = r.child(n, p, "coarsen", false)) {
    const std::string q = p + ".coarsen";
    if (!c.IsMap()) r.fail(q, "must be a map {enabled, theta_coarsen, after}");
    r.checkKeys(c, q, {"enabled", "theta_coarsen", "after"});
    if (auto v = r.child(c, q, "enabled", false)) {
      if (!v.IsScalar() || (v.Scalar() != "true" && v.Scalar() != "false"))
        r.fail(q + ".enabled", "must be true or false");
      a.coarsen = v.Scalar() == "true";
    }
    if (auto v = r.child(c, q, "theta_coarsen", false)) a.theta_coarsen = r.number(v, q + ".theta_coarsen");
    if (!(a.theta_coarsen > 0 && a.theta_coarsen < 1))
      r.fail(q + ".theta_coarsen", "must be in (0, 1), got " + SceneReader::fmt(a.theta_coarsen));
    // A merged parent's error is about twice its children's combined (linear elements,
    // h doubled): below theta / 2 it cannot be marked again at once, so nothing flickers.
    if (a.coarsen && a.marking == AdaptivitySettings::Marking::Max && !(a.theta_coarsen < 0.5 * a.theta))
      r.fail(q + ".theta_coarsen", "must be < theta / 2 = " + SceneReader::fmt(0.5 * a.theta) +
                                       " (hysteresis: a merged element would be refined again at once), got " +
                                       SceneReader::fmt(a.theta_coarsen));
    integerIn(c, q, "after", 1, 1000000, a.coarsen_after);
  }
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (a.max_dofs == 0 && s.tissue.cells.cast<double>().prod() * std::pow(8.0, a.max_level) > 5e7)
    r.fail(p + ".max_level", "a fully refined grid of " + std::to_string(s.tissue.cells.prod()) + " cells at level " +
                                 std::to_string(a.max_level) + " would exceed 5e7 elements; lower max_level, set a coarser grid or a max_dofs budget");
  s.adaptivity = a;
}

void readProbes(const SceneReader& r, const YAML::Node& n, Scene& s) {
  if (!n.IsSequence()) r.fail("probes", "must be a list of {name, point}");
  static const std::regex ident("[A-Za-z0-9_]+");
  std::set<std::string> names;
  for (size_t i = 0; i < n.size(); ++i) {
    const std::string p = "probes[" + std::to_string(i) + "]";
    r.checkKeys(n[i], p, {"name", "point"});
    ProbeScene pr;
    pr.name = r.string(r.child(n[i], p, "name", true), p + ".name");
    if (!std::regex_match(pr.name, ident))
      r.fail(p + ".name", "must be letters, digits and '_' only (it names CSV columns), got '" + pr.name + "'");
    if (!names.insert(pr.name).second) r.fail(p + ".name", "duplicate probe name '" + pr.name + "'");
    pr.point = r.vec3(r.child(n[i], p, "point", true), p + ".point");
    s.probes.push_back(pr);
  }
}

void readTargets(const SceneReader& r, const YAML::Node& n, Scene& s) {
  if (!n.IsSequence()) r.fail("targets", "must be a list of {name, point} or {name, surface}");
  static const std::regex ident("[A-Za-z0-9_]+");
  std::set<std::string> names;
  for (size_t i = 0; i < n.size(); ++i) {
    const std::string p = "targets[" + std::to_string(i) + "]";
    r.checkKeys(n[i], p, {"name", "point", "surface", "scale", "transform", "radius"});
    TargetScene t;
    if (auto v = r.child(n[i], p, "radius", false)) {
      t.radius = r.number(v, p + ".radius");
      if (!(t.radius >= 0)) r.fail(p + ".radius", "must be >= 0 (0: the point itself), got " + SceneReader::fmt(t.radius));
    }
    t.key = p;
    t.name = r.string(r.child(n[i], p, "name", true), p + ".name");
    if (!std::regex_match(t.name, ident))
      r.fail(p + ".name", "must be letters, digits and '_' only (it names CSV columns and frames), got '" + t.name + "'");
    if (!names.insert(t.name).second) r.fail(p + ".name", "duplicate target name '" + t.name + "'");
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
  r.checkKeys(n, p, {"gravity", "csf_level", "density", "skull", "target_shift", "target", "replan", "load_steps", "tolerance",
                  "coarse_start"});
  BrainShiftSettings b;
  if (auto v = r.child(n, p, "gravity", false)) b.gravity = r.vec3(v, p + ".gravity");
  if (!(b.gravity.norm() > 0)) r.fail(p + ".gravity", "must be a non-zero vector");
  if (auto v = r.child(n, p, "csf_level", false)) {
    if (v.IsScalar() && v.Scalar() == "all") {
      b.all = true;
    } else {
      r.checkKeys(v, p + ".csf_level", {"point"});
      b.all = false;
      b.csf_point = r.vec3(r.child(v, p + ".csf_level", "point", true), p + ".csf_level.point");
    }
  }
  if (n["density"]) b.density = r.positive(n, p, "density");
  if (auto sk = r.child(n, p, "skull", false)) {
    const std::string q = p + ".skull";
    r.checkKeys(sk, q, {"gap", "surface", "scale", "transform", "enabled", "support"});
    for (const char* key : {"enabled", "support"})
      if (auto v = r.child(sk, q, key, false))
        (std::string(key) == "enabled" ? b.skull_contact : b.skull_support) = r.boolean(v, q + "." + key);
    if (sk["gap"] && sk["surface"]) r.fail(q, "give either 'gap' or 'surface', not both");
    if (sk["gap"]) {
      b.gap = r.number(sk["gap"], q + ".gap");
      if (b.gap < 0) r.fail(q + ".gap", "must be >= 0");
    }
    if (sk["surface"]) b.skull = readSurfaceFile(r, sk["surface"], q + ".surface", readTransform(r, sk, q, s.tissue.geometry.transform));
  }
  if (n["target_shift"]) b.target_shift = r.positive(n, p, "target_shift");
  if (auto v = r.child(n, p, "target", false)) b.target = r.string(v, p + ".target");
  if (auto v = r.child(n, p, "replan", false)) {
    b.replan = r.boolean(v, p + ".replan");
    if (b.replan && s.needles.empty()) r.fail(p + ".replan", "re-aims the needles: the scene has none");
  }
  if (b.target_shift || !b.target.empty() || b.replan) {
    if (s.targets.empty())
      r.fail(p + (b.replan ? ".replan" : b.target.empty() ? ".target_shift" : ".target"), "needs a target (the scene has none)");
    if (b.target.empty()) b.target = s.targets.front().name;
    bool found = false;
    for (const auto& t : s.targets) found = found || t.name == b.target;
    if (!found) r.fail(p + ".target", "no target named '" + b.target + "'");
  }
  if (auto v = r.child(n, p, "load_steps", false)) {
    const long long k = r.integer(v, p + ".load_steps");
    if (k < 1 || k > 1000) r.fail(p + ".load_steps", "must be in [1, 1000]");
    b.load_steps = static_cast<int>(k);
  }
  if (auto v = r.child(n, p, "coarse_start", false)) b.coarse_start = r.boolean(v, p + ".coarse_start");
  if (n["tolerance"]) {
    b.tolerance = r.positive(n, p, "tolerance");
    if (b.tolerance >= 1) r.fail(p + ".tolerance", "must be < 1");
  }
  if (s.tissue.dirichlet.empty()) r.fail("tissue.dirichlet", "brain shift needs clamped regions that hold the brain");
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
  readTime(r, r.child(root, "", "time", true), s);
  if (auto v = r.child(root, "", "solver", false)) readSolver(r, v, s);
  if (auto t = r.child(root, "", "tissue", false)) readTissue(r, t, s);
  else s.has_tissue = false;
  readNeedles(r, root, s);
  if (!s.has_tissue && s.needles.empty()) r.fail("tissue", "missing: a scene needs a tissue, a needle, or both");
  if (auto v = r.child(root, "", "interaction", false)) readInteraction(r, v, s);
  for (auto& nd : s.needles)
    if (nd.bevel.enabled) {
      if (!s.interaction) r.fail(nd.key + ".bevel", "a bevel acts while the tip cuts: the scene needs an 'interaction' section");
      if (std::isnan(nd.bevel.lateral_ratio)) nd.bevel.lateral_ratio = bevelLateralRatio(nd.bevel.angle, s.interaction->friction);
    }
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
  // Goal-oriented adaptivity names targets: they must exist (read after the adaptivity).
  if (s.adaptivity)
    for (size_t i = 0; i < s.adaptivity->goal_targets.size(); ++i) {
      const std::string& name = s.adaptivity->goal_targets[i];
      bool found = false;
      for (const auto& t : s.targets) found = found || t.name == name;
      if (!found) r.fail("adaptivity.goal.targets[" + std::to_string(i) + "]", "no target named '" + name + "' in targets");
    }
  if (s.has_tissue && s.solver.mode == SolverSettings::Mode::Static && s.tissue.dirichlet.empty())
    r.fail("tissue.dirichlet", "static mode needs Dirichlet conditions that hold the body (none given)");
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
