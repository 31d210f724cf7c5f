#pragma once
// The validating YAML reader of scene files (doc/scene_format.md): every accessor names the
// key path in its errors (InputError: file, key, problem), unknown keys are refused, and
// the pieces several sections share (boxes, regions, surface files with their transform,
// unit vectors) are read here once.
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/region.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

struct Scene;

const char* typeName(const YAML::Node& n);

class SceneReader {
 public:
  explicit SceneReader(std::string file) : file_(std::move(file)) {}

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

  bool boolean(const YAML::Node& n, const std::string& key) const {
    try {
      return n.as<bool>();
    } catch (const YAML::Exception&) {
      fail(key, "must be true or false");
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

BoxRegion readBox(const SceneReader& r, const YAML::Node& n, const std::string& path);
// A file named in the scene, relative to the scene file's folder.
std::string resolvePath(const SceneReader& r, const std::string& name);
// {scale, transform: {translation, rpy}} next to a surface file; `base` gives the defaults.
SurfaceTransform readTransform(const SceneReader& r, const YAML::Node& n, const std::string& path,
                               const SurfaceTransform& base = {});
std::shared_ptr<const TriangleMesh> readSurfaceFile(const SceneReader& r, const YAML::Node& n, const std::string& key,
                                                    const SurfaceTransform& t);
Vec3 centerOf(const SceneReader& r, const YAML::Node& n, const std::string& path, double& radius);
// A box, a sphere or a surface_distance region; s: the scene so far (for 'tissue', the
// organ surface), or nullptr.
Region readRegion(const SceneReader& r, const YAML::Node& n, const std::string& path, const Scene* s = nullptr);
Vec3 unitVector(const SceneReader& r, const YAML::Node& n, const std::string& key);

}  // namespace needle_sim
