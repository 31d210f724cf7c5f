#include "needle_sim/scene/scene_loader.hpp"

#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <regex>
#include <set>
#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

long Scene::numSteps() const { return static_cast<long>(std::llround(std::ceil(duration / dt - 1e-9))); }

double estimateSolverBytes(const Vec3i& cells) {
  const double nodes = double(cells[0] + 1) * (cells[1] + 1) * (cells[2] + 1);
  const double elements = double(cells[0]) * cells[1] * cells[2];
  const double dofs = 3 * nodes;
  // Factor fill of a 3D grid under nested dissection grows like n^(4/3); scaled from the
  // 28,611-DOF phantom (14.5 M nonzeros, DESIGN.md §6).
  const double lnz = 14.5e6 * std::pow(dofs / 28611.0, 4.0 / 3.0);
  const double matrix = 81.0 / 2 * dofs * 12;     // upper triangle, value + index
  const double positions = elements * 576 * 4.0;  // assembly scatter map
  const double vectors = dofs * 8 * 30;
  return 8 * 1.5 * lnz + matrix + positions + vectors;
}

namespace {

const char* typeName(const YAML::Node& n) {
  switch (n.Type()) {
    case YAML::NodeType::Map: return "a map";
    case YAML::NodeType::Sequence: return "a list";
    case YAML::NodeType::Scalar: return "a scalar";
    case YAML::NodeType::Null: return "empty";
    default: return "undefined";
  }
}

// Validating reader: every accessor names the key path in its errors.
class Reader {
 public:
  explicit Reader(std::string file) : file_(std::move(file)) {}

  [[noreturn]] void fail(const std::string& key, const std::string& problem) const {
    throw InputError(file_, key, problem);
  }

  static std::string join(const std::string& path, const std::string& key) {
    return path.empty() ? key : path + "." + key;
  }

  void requireMap(const YAML::Node& n, const std::string& path) const {
    if (!n.IsMap()) fail(path, std::string("must be a map, got ") + typeName(n));
  }

  // Rejects keys outside `allowed`.
  void checkKeys(const YAML::Node& n, const std::string& path, const std::vector<std::string>& allowed) const {
    requireMap(n, path);
    for (const auto& kv : n) {
      if (!kv.first.IsScalar()) fail(path, std::string("has a key that is not a name (a ") + typeName(kv.first) + ")");
      const std::string k = kv.first.as<std::string>();
      if (std::find(allowed.begin(), allowed.end(), k) == allowed.end()) {
        std::string list;
        for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
        fail(join(path, k), "unknown key (allowed here: " + list + ")");
      }
    }
  }

  YAML::Node child(const YAML::Node& n, const std::string& path, const std::string& key, bool required) const {
    YAML::Node c = n[key];
    if (!c.IsDefined() || c.IsNull()) {
      if (required) fail(join(path, key), "missing required key");
      return YAML::Node(YAML::NodeType::Undefined);
    }
    return c;
  }

  double number(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(key, std::string("must be a number, got ") + typeName(n));
    double v;
    try {
      v = n.as<double>();
    } catch (const YAML::Exception&) {
      fail(key, "must be a number, got '" + n.Scalar() + "'");
    }
    if (!std::isfinite(v)) fail(key, "must be finite, got '" + n.Scalar() + "'");
    return v;
  }

  long long integer(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(key, std::string("must be an integer, got ") + typeName(n));
    try {
      return n.as<long long>();
    } catch (const YAML::Exception&) {
      fail(key, "must be an integer, got '" + n.Scalar() + "'");
    }
  }

  std::string string(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(key, std::string("must be a string, got ") + typeName(n));
    return n.Scalar();
  }

  Vec3 vec3(const YAML::Node& n, const std::string& key) const {
    if (!n.IsSequence() || n.size() != 3) fail(key, "must be a list of 3 numbers [x, y, z]");
    Vec3 v;
    for (int i = 0; i < 3; ++i) v[i] = number(n[i], key + "[" + std::to_string(i) + "]");
    return v;
  }

  double positive(const YAML::Node& parent, const std::string& path, const std::string& key) const {
    const std::string k = join(path, key);
    const double v = number(child(parent, path, key, true), k);
    if (!(v > 0)) fail(k, "must be > 0, got " + fmt(v));
    return v;
  }

  static std::string fmt(double v) {
    std::ostringstream s;
    s << v;
    return s.str();
  }

  const std::string& file() const { return file_; }

 private:
  std::string file_;
};

BoxRegion readBox(const Reader& r, const YAML::Node& n, const std::string& path) {
  r.checkKeys(n, path, {"min", "max"});
  BoxRegion b;
  b.min = r.vec3(r.child(n, path, "min", true), path + ".min");
  b.max = r.vec3(r.child(n, path, "max", true), path + ".max");
  for (int d = 0; d < 3; ++d)
    if (!(b.max[d] > b.min[d]))
      r.fail(path, "empty or inverted box: max must exceed min in every coordinate (axis " +
                       std::string(1, "xyz"[d]) + ": min " + Reader::fmt(b.min[d]) + ", max " +
                       Reader::fmt(b.max[d]) + ")");
  return b;
}

// A file named in the scene, relative to the scene file's folder.
std::string resolvePath(const Reader& r, const std::string& name) {
  if (name.empty() || name[0] == '/') return name;
  const std::string& f = r.file();
  const auto slash = f.find_last_of('/');
  return slash == std::string::npos ? name : f.substr(0, slash + 1) + name;
}

// {scale, transform: {translation, rpy}} next to a surface file; `base` gives the defaults.
SurfaceTransform readTransform(const Reader& r, const YAML::Node& n, const std::string& path,
                               const SurfaceTransform& base = {}) {
  SurfaceTransform t = base;
  if (auto v = r.child(n, path, "scale", false)) {
    t.scale = r.number(v, Reader::join(path, "scale"));
    if (!(t.scale > 0)) r.fail(Reader::join(path, "scale"), "must be > 0, got " + Reader::fmt(t.scale));
  }
  if (auto tr = r.child(n, path, "transform", false)) {
    const std::string p = Reader::join(path, "transform");
    r.checkKeys(tr, p, {"translation", "rpy"});
    t.translation = Vec3::Zero();
    t.rotation = Mat3::Identity();
    if (auto v = r.child(tr, p, "translation", false)) t.translation = r.vec3(v, p + ".translation");
    if (auto v = r.child(tr, p, "rpy", false)) {
      const Vec3 a = r.vec3(v, p + ".rpy");  // roll, pitch, yaw [rad], fixed axes x, y, z
      t.rotation = (Eigen::AngleAxisd(a[2], Vec3::UnitZ()) * Eigen::AngleAxisd(a[1], Vec3::UnitY()) *
                    Eigen::AngleAxisd(a[0], Vec3::UnitX()))
                       .toRotationMatrix();
    }
  }
  return t;
}

std::shared_ptr<const TriangleMesh> readSurfaceFile(const Reader& r, const YAML::Node& n, const std::string& key,
                                                    const SurfaceTransform& t) {
  const std::string name = r.string(n, key);
  return std::make_shared<const TriangleMesh>(loadTriangleMesh(resolvePath(r, name), t, r.file(), key));
}

Vec3 centerOf(const Reader& r, const YAML::Node& n, const std::string& path, double& radius) {
  r.checkKeys(n, path, {"center", "radius"});
  const Vec3 c = r.vec3(r.child(n, path, "center", true), path + ".center");
  radius = r.positive(n, path, "radius");
  return c;
}

Region readRegion(const Reader& r, const YAML::Node& n, const std::string& path, const Scene* s = nullptr) {
  r.checkKeys(n, path, {"box", "sphere", "surface_distance"});
  const int given = (n["box"] ? 1 : 0) + (n["sphere"] ? 1 : 0) + (n["surface_distance"] ? 1 : 0);
  if (given != 1) r.fail(path, "give exactly one of 'box', 'sphere', 'surface_distance'");
  Region reg;
  if (n["box"]) {
    reg.box = readBox(r, n["box"], path + ".box");
  } else if (n["sphere"]) {
    reg.kind = Region::Kind::Sphere;
    reg.center = centerOf(r, n["sphere"], path + ".sphere", reg.radius);
  } else {
    const std::string p = path + ".surface_distance";
    const auto sd = n["surface_distance"];
    r.checkKeys(sd, p, {"surface", "scale", "transform", "distance", "patch"});
    reg.kind = Region::Kind::SurfaceDistance;
    reg.distance = r.positive(sd, p, "distance");
    const auto f = r.child(sd, p, "surface", true);
    const bool organ = f.IsScalar() && f.Scalar() == "tissue";
    if (organ) {
      if (!s || !s->tissue.geometry.surface)
        r.fail(p + ".surface", "'tissue' names the organ surface, but tissue.geometry has no surface");
      if (sd["scale"] || sd["transform"]) r.fail(p, "'scale'/'transform' do not apply to the organ surface");
      reg.surface = s->tissue.geometry.surface;
    } else {
      const SurfaceTransform base = s ? s->tissue.geometry.transform : SurfaceTransform{};
      reg.surface = readSurfaceFile(r, f, p + ".surface", readTransform(r, sd, p, base));
    }
    Region patch;
    bool has_patch = false;
    if (auto pa = r.child(sd, p, "patch", false)) {
      patch = readRegion(r, pa, p + ".patch", s);
      if (patch.kind == Region::Kind::SurfaceDistance) r.fail(p + ".patch", "must be a 'box' or a 'sphere'");
      has_patch = true;
    }
    const TriangleMesh& m = *reg.surface;
    reg.patch_min = Vec3::Constant(1e300);
    reg.patch_max = Vec3::Constant(-1e300);
    for (int t = 0; t < m.numTriangles(); ++t) {
      const auto& tr = m.triangle(t);
      const Vec3 c = (m.vertex(tr[0]) + m.vertex(tr[1]) + m.vertex(tr[2])) / 3;
      if (has_patch && !patch.contains(c, 0)) continue;
      reg.patch.push_back(t);
      for (int k : tr) {
        reg.patch_min = reg.patch_min.cwiseMin(m.vertex(k));
        reg.patch_max = reg.patch_max.cwiseMax(m.vertex(k));
      }
    }
    if (reg.patch.empty()) r.fail(p + ".patch", "contains no triangle of the surface");
  }
  return reg;
}

void readTime(const Reader& r, const YAML::Node& n, Scene& s) {
  r.checkKeys(n, "time", {"dt", "duration"});
  s.dt = r.positive(n, "time", "dt");
  s.duration = r.positive(n, "time", "duration");
  if (s.duration / s.dt > 1e9) r.fail("time", "duration / dt exceeds 1e9 steps");
}

void readSolver(const Reader& r, const YAML::Node& n, Scene& s) {
  r.checkKeys(n, "solver", {"mode", "rayleigh", "static", "linear"});
  if (auto m = r.child(n, "solver", "mode", false)) {
    const std::string mode = r.string(m, "solver.mode");
    if (mode == "dynamic") s.solver.mode = SolverScene::Mode::Dynamic;
    else if (mode == "static") s.solver.mode = SolverScene::Mode::Static;
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
    r.checkKeys(st, "solver.static", {"tolerance", "max_iterations"});
    if (st["tolerance"]) s.solver.static_tolerance = r.positive(st, "solver.static", "tolerance");
    if (auto it = r.child(st, "solver.static", "max_iterations", false)) {
      const long long v = r.integer(it, "solver.static.max_iterations");
      if (v < 1 || v > 100000) r.fail("solver.static.max_iterations", "must be in [1, 100000]");
      s.solver.static_max_iterations = static_cast<int>(v);
    }
  }
  if (auto li = r.child(n, "solver", "linear", false)) {
    const std::string p = "solver.linear";
    r.checkKeys(li, p, {"method", "tolerance", "max_iterations", "refresh_iterations", "refactor_every", "ordering"});
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
        const long long x = r.integer(v, Reader::join(p, key));
        if (x < lo || x > 1000000) r.fail(Reader::join(p, key), "must be in [" + std::to_string(lo) + ", 1000000]");
        out = static_cast<int>(x);
      }
    };
    readInt("max_iterations", 1, L.max_iterations);
    readInt("refresh_iterations", 0, L.refresh_iterations);
    readInt("refactor_every", 0, L.refactor_every);
    if (auto o = r.child(li, p, "ordering", false)) {
      const std::string v = r.string(o, p + ".ordering");
      if (v == "auto") L.ordering = Ordering::Auto;
      else if (v == "amd") L.ordering = Ordering::Amd;
      else if (v == "metis") L.ordering = Ordering::Metis;
      else r.fail(p + ".ordering", "must be 'auto', 'amd' or 'metis', got '" + v + "'");
    }
  }
}

void readTissue(const Reader& r, const YAML::Node& n, Scene& s) {
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
             "gives a grid of " + Reader::fmt(T.cells.cast<double>().prod()) + " cells over the surface's box: too many");
  }
  const double need = estimateSolverBytes(T.cells);
  const double have = double(sysconf(_SC_PHYS_PAGES)) * double(sysconf(_SC_PAGE_SIZE));
  if (need > 0.6 * have) {
    std::ostringstream m;
    m.precision(3);
    m << "grid of " << double(T.cells[0]) * T.cells[1] * T.cells[2] << " cells needs an estimated "
      << need / (1 << 30) << " GiB, more than 60% of this machine's " << have / (1 << 30) << " GiB";
    r.fail("tissue.grid.cells", m.str());
  }
  // material
  const auto mat = r.child(n, "tissue", "material", true);
  r.checkKeys(mat, "tissue.material", {"young", "poisson", "density"});
  T.material.young = r.positive(mat, "tissue.material", "young");
  T.material.poisson = r.number(r.child(mat, "tissue.material", "poisson", true), "tissue.material.poisson");
  if (!(T.material.poisson > -1 && T.material.poisson < 0.5))
    r.fail("tissue.material.poisson", "must be in (-1, 0.5), got " + Reader::fmt(T.material.poisson));
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

Vec3 unitVector(const Reader& r, const YAML::Node& n, const std::string& key) {
  const Vec3 d = r.vec3(n, key);
  if (std::abs(d.norm() - 1) > 1e-6)
    r.fail(key, "must be a unit vector, got length " + Reader::fmt(d.norm()));
  return d;
}

NeedleScene readNeedle(const Reader& r, const YAML::Node& n, const std::string& p) {
  r.checkKeys(n, p, {"name", "length", "radius", "inner_radius", "young", "poisson", "density", "elements", "base",
                     "motion", "tip_force", "tip_moment", "gravity"});
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
      r.fail(p + ".inner_radius", "must be smaller than radius (" + Reader::fmt(s.inner_radius) +
                                      " >= " + Reader::fmt(s.radius) + ")");
  }
  s.young = r.positive(n, p, "young");
  s.poisson = r.number(r.child(n, p, "poisson", true), p + ".poisson");
  if (!(s.poisson > -1 && s.poisson < 0.5)) r.fail(p + ".poisson", "must be in (-1, 0.5), got " + Reader::fmt(s.poisson));
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
  if (auto m = r.child(n, p, "motion", false)) {
    if (!m.IsSequence()) r.fail(p + ".motion", "must be a list of {t, advance} or {t, position, direction}");
    for (size_t i = 0; i < m.size(); ++i) {
      const std::string q = p + ".motion[" + std::to_string(i) + "]";
      r.checkKeys(m[i], q, {"t", "advance", "position", "direction", "roll"});
      NeedleMotionKey k;
      k.t = r.number(r.child(m[i], q, "t", true), q + ".t");
      if (k.t < 0) r.fail(q + ".t", "must be >= 0");
      if (i > 0 && !(k.t > s.motion.back().t))
        r.fail(q + ".t", "times must increase strictly (" + Reader::fmt(k.t) + " after " + Reader::fmt(s.motion.back().t) + ")");
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
      s.motion.push_back(k);
    }
  }
  return s;
}

void readNeedles(const Reader& r, const YAML::Node& root, Scene& s) {
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

void readInteraction(const Reader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "interaction";
  r.checkKeys(n, p, {"puncture_force", "cutting_force", "friction", "shaft_spacing", "solver"});
  InteractionSettings is;
  auto nonNegative = [&](const char* key) {
    const std::string k = Reader::join(p, key);
    const double v = r.number(r.child(n, p, key, true), k);
    if (v < 0) r.fail(k, "must be >= 0, got " + Reader::fmt(v));
    return v;
  };
  is.puncture_force = nonNegative("puncture_force");
  is.cutting_force = nonNegative("cutting_force");
  is.friction = nonNegative("friction");
  is.shaft_spacing = r.positive(n, p, "shaft_spacing");
  if (auto sv = r.child(n, p, "solver", false)) {
    r.checkKeys(sv, p + ".solver", {"tolerance", "max_iterations"});
    if (sv["tolerance"]) is.tolerance = r.positive(sv, p + ".solver", "tolerance");
    if (auto it = r.child(sv, p + ".solver", "max_iterations", false)) {
      const long long v = r.integer(it, p + ".solver.max_iterations");
      if (v < 1 || v > 1000000) r.fail(p + ".solver.max_iterations", "must be in [1, 1000000]");
      is.max_iterations = static_cast<int>(v);
    }
  }
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (s.needles.empty()) r.fail(p, "needs a needle (the scene has none)");
  if (s.solver.mode != SolverScene::Mode::Dynamic) r.fail(p, "needs solver.mode: dynamic");
  s.interaction = is;
}

void readAdaptivity(const Reader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "adaptivity";
  if (!n.IsMap()) r.fail(p, "must be a map {estimator, marking, theta, max_level, ...}");
  r.checkKeys(n, p, {"estimator", "marking", "theta", "max_level", "max_dofs", "tolerance", "every_steps", "coarsen"});
  AdaptivitySettings a;
  if (auto v = r.child(n, p, "estimator", false)) {
    const std::string e = r.string(v, p + ".estimator");
    if (e != "spr") r.fail(p + ".estimator", "unknown estimator '" + e + "' (available: spr)");
  }
  if (auto v = r.child(n, p, "marking", false)) {
    const std::string m = r.string(v, p + ".marking");
    if (m == "max") a.marking = AdaptivitySettings::Marking::Max;
    else if (m == "bulk") a.marking = AdaptivitySettings::Marking::Bulk;
    else r.fail(p + ".marking", "must be max or bulk, got '" + m + "'");
  }
  a.theta = r.number(r.child(n, p, "theta", true), p + ".theta");
  if (!(a.theta > 0 && a.theta <= 1)) r.fail(p + ".theta", "must be in (0, 1], got " + Reader::fmt(a.theta));
  auto integerIn = [&](const YAML::Node& parent, const std::string& path, const char* key, long long lo, long long hi,
                       int& out) {
    if (auto v = r.child(parent, path, key, false)) {
      const std::string k = Reader::join(path, key);
      const long long x = r.integer(v, k);
      if (x < lo || x > hi)
        r.fail(k, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got " + std::to_string(x));
      out = static_cast<int>(x);
    }
  };
  integerIn(n, p, "max_level", 0, 6, a.max_level);
  integerIn(n, p, "max_dofs", 0, 100000000, a.max_dofs);
  integerIn(n, p, "every_steps", 1, 1000000000, a.every_steps);
  if (auto v = r.child(n, p, "tolerance", false)) {
    a.tolerance = r.number(v, p + ".tolerance");
    if (a.tolerance < 0) r.fail(p + ".tolerance", "must be >= 0, got " + Reader::fmt(a.tolerance));
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
      r.fail(q + ".theta_coarsen", "must be in (0, 1), got " + Reader::fmt(a.theta_coarsen));
    // A merged parent's error is about twice its children's combined (linear elements,
    // h doubled): below theta / 2 it cannot be marked again at once, so nothing flickers.
    if (a.coarsen && a.marking == AdaptivitySettings::Marking::Max && !(a.theta_coarsen < 0.5 * a.theta))
      r.fail(q + ".theta_coarsen", "must be < theta / 2 = " + Reader::fmt(0.5 * a.theta) +
                                       " (hysteresis: a merged element would be refined again at once), got " +
                                       Reader::fmt(a.theta_coarsen));
    integerIn(c, q, "after", 1, 1000000, a.coarsen_after);
  }
  if (!s.has_tissue) r.fail(p, "needs a tissue (the scene has none)");
  if (a.max_dofs == 0 && s.tissue.cells.cast<double>().prod() * std::pow(8.0, a.max_level) > 5e7)
    r.fail(p + ".max_level", "a fully refined grid of " + std::to_string(s.tissue.cells.prod()) + " cells at level " +
                                 std::to_string(a.max_level) + " would exceed 5e7 elements; lower max_level, set a coarser grid or a max_dofs budget");
  s.adaptivity = a;
}

void readProbes(const Reader& r, const YAML::Node& n, Scene& s) {
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

void readTargets(const Reader& r, const YAML::Node& n, Scene& s) {
  if (!n.IsSequence()) r.fail("targets", "must be a list of {name, point} or {name, surface}");
  static const std::regex ident("[A-Za-z0-9_]+");
  std::set<std::string> names;
  for (size_t i = 0; i < n.size(); ++i) {
    const std::string p = "targets[" + std::to_string(i) + "]";
    r.checkKeys(n[i], p, {"name", "point", "surface", "scale", "transform"});
    TargetScene t;
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

void readBrainShift(const Reader& r, const YAML::Node& n, Scene& s) {
  const std::string p = "brain_shift";
  r.checkKeys(n, p, {"gravity", "csf_level", "density", "skull", "target_shift", "target", "load_steps", "tolerance"});
  BrainShiftScene b;
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
      if (auto v = r.child(sk, q, key, false)) {
        try {
          (std::string(key) == "enabled" ? b.skull_contact : b.skull_support) = v.as<bool>();
        } catch (const YAML::Exception&) {
          r.fail(q + "." + key, "must be true or false");
        }
      }
    if (sk["gap"] && sk["surface"]) r.fail(q, "give either 'gap' or 'surface', not both");
    if (sk["gap"]) {
      b.gap = r.number(sk["gap"], q + ".gap");
      if (b.gap < 0) r.fail(q + ".gap", "must be >= 0");
    }
    if (sk["surface"]) b.skull = readSurfaceFile(r, sk["surface"], q + ".surface", readTransform(r, sk, q, s.tissue.geometry.transform));
  }
  if (n["target_shift"]) b.target_shift = r.positive(n, p, "target_shift");
  if (auto v = r.child(n, p, "target", false)) b.target = r.string(v, p + ".target");
  if (b.target_shift || !b.target.empty()) {
    if (s.targets.empty()) r.fail(p + (b.target.empty() ? ".target_shift" : ".target"), "needs a target (the scene has none)");
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
  if (n["tolerance"]) {
    b.tolerance = r.positive(n, p, "tolerance");
    if (b.tolerance >= 1) r.fail(p + ".tolerance", "must be < 1");
  }
  if (s.tissue.dirichlet.empty()) r.fail("tissue.dirichlet", "brain shift needs clamped regions that hold the brain");
  s.brain_shift = b;
}

// Applies "a.b.c=value" to the tree, creating maps on the way; indices select list items.
void applyOverride(YAML::Node root, const std::string& spec, const std::string& file) {
  const auto eq = spec.find('=');
  if (eq == std::string::npos || eq == 0)
    throw InputError(file, spec, "override must have the form key.path=value");
  const std::string path = spec.substr(0, eq);
  YAML::Node value;
  try {
    value = YAML::Load(spec.substr(eq + 1));
  } catch (const YAML::Exception& e) {
    throw InputError(file, path, "override value is not valid YAML: " + e.msg);
  }
  std::vector<std::string> parts;
  std::stringstream ss(path);
  for (std::string p; std::getline(ss, p, '.');) {
    if (p.empty()) throw InputError(file, path, "empty component in override key");
    parts.push_back(p);
  }
  YAML::Node cur = root;
  for (size_t i = 0; i < parts.size(); ++i) {
    const std::string& k = parts[i];
    const bool last = i + 1 == parts.size();
    if (cur.IsSequence()) {
      size_t idx;
      try {
        size_t used = 0;
        idx = std::stoul(k, &used);
        if (used != k.size()) throw std::invalid_argument(k);
      } catch (const std::exception&) {
        throw InputError(file, path, "'" + k + "' must be a list index");
      }
      if (idx >= cur.size())
        throw InputError(file, path, "list index " + k + " out of range (size " + std::to_string(cur.size()) + ")");
      if (last) cur[idx] = value;
      else cur.reset(YAML::Node(cur[idx]));
      continue;
    }
    if (!cur.IsMap() && !cur.IsNull())
      throw InputError(file, path, "cannot descend into '" + k + "': parent is not a map");
    if (last) {
      cur[k] = value;
    } else {
      if (!cur[k] || cur[k].IsNull()) cur[k] = YAML::Node(YAML::NodeType::Map);
      YAML::Node next = cur[k];
      cur.reset(next);
    }
  }
}

Scene build(YAML::Node root, const std::string& file, const std::vector<std::string>& overrides) {
  Reader r(file);
  if (!root.IsMap()) r.fail("", std::string("scene must be a YAML map at the top level, got ") + typeName(root));
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
  if (s.has_tissue && s.solver.mode == SolverScene::Mode::Static && s.tissue.dirichlet.empty())
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
