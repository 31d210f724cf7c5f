#include "needle_sim/scene/yaml_reader.hpp"

#include <cmath>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

const char* typeName(const YAML::Node& n) {
  switch (n.Type()) {
    case YAML::NodeType::Map: return "a map";
    case YAML::NodeType::Sequence: return "a list";
    case YAML::NodeType::Scalar: return "a scalar";
    case YAML::NodeType::Null: return "empty";
    default: return "undefined";
  }
}


BoxRegion readBox(const SceneReader& r, const YAML::Node& n, const std::string& path) {
  r.checkKeys(n, path, {"min", "max"});
  BoxRegion b;
  b.min = r.vec3(r.child(n, path, "min", true), path + ".min");
  b.max = r.vec3(r.child(n, path, "max", true), path + ".max");
  for (int d = 0; d < 3; ++d)
    if (!(b.max[d] > b.min[d]))
      r.fail(path, "empty or inverted box: max must exceed min in every coordinate (axis " +
                       std::string(1, "xyz"[d]) + ": min " + SceneReader::fmt(b.min[d]) + ", max " +
                       SceneReader::fmt(b.max[d]) + ")");
  return b;
}

// A file named in the scene, relative to the scene file's folder.
std::string resolvePath(const SceneReader& r, const std::string& name) {
  if (name.empty() || name[0] == '/') return name;
  const std::string& f = r.file();
  const auto slash = f.find_last_of('/');
  return slash == std::string::npos ? name : f.substr(0, slash + 1) + name;
}

// {scale, transform: {translation, rpy}} next to a surface file; `base` gives the defaults.
SurfaceTransform readTransform(const SceneReader& r, const YAML::Node& n, const std::string& path,
                               const SurfaceTransform& base) {
  SurfaceTransform t = base;
  if (auto v = r.child(n, path, "scale", false)) {
    t.scale = r.number(v, SceneReader::join(path, "scale"));
    if (!(t.scale > 0)) r.fail(SceneReader::join(path, "scale"), "must be > 0, got " + SceneReader::fmt(t.scale));
  }
  if (auto tr = r.child(n, path, "transform", false)) {
    const std::string p = SceneReader::join(path, "transform");
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

std::shared_ptr<const TriangleMesh> readSurfaceFile(const SceneReader& r, const YAML::Node& n, const std::string& key,
                                                    const SurfaceTransform& t) {
  const std::string name = r.string(n, key);
  return std::make_shared<const TriangleMesh>(loadTriangleMesh(resolvePath(r, name), t, r.file(), key));
}

Vec3 centerOf(const SceneReader& r, const YAML::Node& n, const std::string& path, double& radius) {
  r.checkKeys(n, path, {"center", "radius"});
  const Vec3 c = r.vec3(r.child(n, path, "center", true), path + ".center");
  radius = r.positive(n, path, "radius");
  return c;
}

Region readRegion(const SceneReader& r, const YAML::Node& n, const std::string& path, const Scene* s) {
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

Vec3 unitVector(const SceneReader& r, const YAML::Node& n, const std::string& key) {
  const Vec3 d = r.vec3(n, key);
  if (std::abs(d.norm() - 1) > 1e-6)
    r.fail(key, "must be a unit vector, got length " + SceneReader::fmt(d.norm()));
  return d;
}

}  // namespace needle_sim
