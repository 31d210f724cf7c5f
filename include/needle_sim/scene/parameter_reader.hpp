#pragma once
// Reads a settings struct's declared keys (core/parameters.hpp) from a scene section: each
// key present is read as its kind (a number, an integer, true/false, [x, y, z], one of the
// names, a string), a required key that is missing is refused, and so is any key the section
// neither declares nor names among its `structural` keys (the lists and alternatives the
// loader reads itself). Every map level on the way to a declared key is checked alike. The
// values' ranges are checked after (Parameters::validate, by scene_check.hpp).
#include <map>
#include <set>
#include <string>
#include <vector>

#include "needle_sim/core/parameters.hpp"
#include "needle_sim/scene/yaml_reader.hpp"

namespace needle_sim {

// The node at a dotted path below `root` (Undefined when absent or null); an intermediate
// that is present but not a map is refused. (No YAML::Node is assigned to another: yaml-cpp's
// assignment would rewrite the tree.)
inline YAML::Node nodeAt(const SceneReader& r, const YAML::Node& root, const std::string& prefix,
                         const std::string& dotted) {
  std::vector<YAML::Node> chain{root};
  std::string path = prefix;
  size_t from = 0;
  while (from <= dotted.size() && !dotted.empty()) {
    const size_t dot = dotted.find('.', from);
    const std::string part = dotted.substr(from, dot == std::string::npos ? std::string::npos : dot - from);
    const YAML::Node& cur = chain.back();
    if (!cur.IsMap()) r.fail(path, std::string("must be a map, got ") + typeName(cur));
    chain.push_back(cur[part]);
    path = SceneReader::join(path, part);
    if (!chain.back().IsDefined() || chain.back().IsNull()) return YAML::Node(YAML::NodeType::Undefined);
    if (dot == std::string::npos) break;
    from = dot + 1;
  }
  return chain.back();
}

// (S is the table's struct; `out` may be a struct derived from it, e.g. TissueScene.)
template <class S>
struct ParametersOf {
  using type = S;
};
template <class S>
void readParameters(const SceneReader& r, const YAML::Node& section, const std::string& prefix,
                    const Parameters<S>& params, typename ParametersOf<S>::type& out,
                    const std::vector<std::string>& structural = {}) {
  // The keys allowed at each map level: the path's next component of every declared and
  // structural key.
  std::map<std::string, std::vector<std::string>> allowed;
  auto allow = [&](const std::string& key) {
    std::string level;
    size_t from = 0;
    while (true) {
      const size_t dot = key.find('.', from);
      const std::string part = key.substr(from, dot == std::string::npos ? std::string::npos : dot - from);
      auto& list = allowed[level];
      if (std::find(list.begin(), list.end(), part) == list.end()) list.push_back(part);
      if (dot == std::string::npos) break;
      level = SceneReader::join(level, part);
      from = dot + 1;
    }
  };
  for (const auto& e : params.entries()) allow(e.declaration.key);
  for (const auto& k : structural) allow(k);
  for (const auto& [level, keys] : allowed) {
    const YAML::Node n = level.empty() ? section : nodeAt(r, section, prefix, level);
    if (n.IsDefined()) r.checkKeys(n, level.empty() ? prefix : SceneReader::join(prefix, level), keys);
  }
  for (const auto& e : params.entries()) {
    const ParameterDeclaration& d = e.declaration;
    const std::string key = SceneReader::join(prefix, d.key);
    const YAML::Node n = nodeAt(r, section, prefix, d.key);
    if (!n.IsDefined()) {
      if (d.required) r.fail(key, "missing required key");
      continue;
    }
    void* p = e.field(out);
    switch (d.kind) {
      case ParameterKind::Real:
        if (e.optional_real) *static_cast<std::optional<double>*>(p) = r.number(n, key);
        else *static_cast<double*>(p) = r.number(n, key);
        break;
      case ParameterKind::Integer: {
        const long long v = r.integer(n, key);
        if (!d.range.contains(static_cast<double>(v)))
          r.fail(key, "must be " + d.range.text() + ", got " + std::to_string(v));
        *static_cast<int*>(p) = static_cast<int>(v);
        break;
      }
      case ParameterKind::Flag:
        *static_cast<bool*>(p) = r.boolean(n, key);
        break;
      case ParameterKind::Vector:
        *static_cast<Vec3*>(p) = r.vec3(n, key);
        break;
      case ParameterKind::Text:
        *static_cast<std::string*>(p) = r.string(n, key);
        break;
      case ParameterKind::Choice: {
        const std::string v = r.string(n, key);
        const auto it = std::find(d.choices.begin(), d.choices.end(), v);
        if (it == d.choices.end()) r.fail(key, "must be one of " + d.type() + ", got '" + v + "'");
        e.set_int(p, static_cast<int>(it - d.choices.begin()));
        break;
      }
    }
  }
}

}  // namespace needle_sim
