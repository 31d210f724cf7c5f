#include "needle_sim/scene/scene_overrides.hpp"

#include <fstream>
#include <sstream>
#include <vector>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

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

namespace {

// base <- over: maps merged key by key (recursively), anything else replaced.
YAML::Node merged(const YAML::Node& base, const YAML::Node& over) {
  if (!base.IsMap() || !over.IsMap()) return YAML::Clone(over);
  YAML::Node out = YAML::Clone(base);
  for (const auto& kv : over) {
    const std::string k = kv.first.as<std::string>();
    out[k] = out[k] ? merged(out[k], kv.second) : YAML::Clone(kv.second);
  }
  return out;
}

}  // namespace

YAML::Node resolveExtends(const YAML::Node& root, const std::string& file, int depth) {
  if (!root.IsMap() || !root["extends"]) return root;
  const YAML::Node e = root["extends"];
  if (!e.IsScalar()) throw InputError(file, "extends", "must be the name of a scene file");
  if (depth > 16) throw InputError(file, "extends", "more than 16 levels of extends (a cycle?)");
  std::string name = e.Scalar();
  if (!name.empty() && name[0] != '/') {
    const auto slash = file.find_last_of('/');
    if (slash != std::string::npos) name = file.substr(0, slash + 1) + name;
  }
  std::ifstream in(name);
  if (!in) throw InputError(file, "extends", "cannot open the base scene '" + name + "'");
  std::stringstream ss;
  ss << in.rdbuf();
  YAML::Node base;
  try {
    base = YAML::Load(ss.str());
  } catch (const YAML::Exception& x) {
    throw InputError(name, "", "not valid YAML: " + x.msg + " (line " + std::to_string(x.mark.line + 1) + ")");
  }
  if (!base.IsMap()) throw InputError(name, "", "a base scene must be a YAML map at the top level");
  base = resolveExtends(base, name, depth + 1);
  YAML::Node over = YAML::Clone(root);
  over.remove("extends");
  YAML::Node out = merged(base, over);
  // A derived scene is named after its own file unless it says otherwise.
  if (!over["name"]) out.remove("name");
  return out;
}

}  // namespace needle_sim
