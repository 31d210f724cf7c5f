#pragma once
// Changing a scene without editing it (doc/scene_format.md): `--set key.path=value`
// overrides (the same in the node's ~set), and `extends: base.yaml`, a scene that is another
// with a few keys changed (e.g. only the grid size): the base is loaded first (relative to
// this file's folder, recursively) and this file's keys are merged into it, maps key by
// key, anything else replaced.
#include <yaml-cpp/yaml.h>

#include <string>

namespace needle_sim {

// Applies "a.b.c=value" to the tree, creating maps on the way; indices select list items.
// Throws InputError(file, key, problem).
void applyOverride(YAML::Node root, const std::string& spec, const std::string& file);
// The tree with its `extends` chain resolved (the key removed). Throws InputError for a
// missing or unreadable base, or a cycle.
YAML::Node resolveExtends(const YAML::Node& root, const std::string& file, int depth = 0);

}  // namespace needle_sim
