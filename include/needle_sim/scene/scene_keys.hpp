#pragma once
// The scene file's value keys, section by section, as their modules declare them
// (core/parameters.hpp): for doc/scene_format.md's key tables (`needle_sim keys --markdown`),
// and for whoever needs a key's type, unit or range (`needle_sim calibrate`'s bounds).
#include <optional>
#include <string>
#include <vector>

#include "needle_sim/core/parameters.hpp"

namespace needle_sim {

struct SceneSection {
  std::string path;    // "time", "solver", "tissue", "tissue.grid", "needle", "needle.bevel", ...
  std::string header;  // the settings header that declares it
  std::vector<ParameterDeclaration> keys;
};
std::vector<SceneSection> sceneSections();

// The declaration of a scene key written as in the file or in --set: "interaction.cutting_force",
// "needles.1.young" or "needles[1].young", "needle.bevel.angle", "tissue.grid.refine";
// std::nullopt for a key that is not a declared value (a list, a region, a geometry).
std::optional<ParameterDeclaration> findSceneKey(const std::string& key);

// One section's table (key, type [unit], default, valid, meaning), Markdown.
std::string sceneKeysMarkdown(const SceneSection& section);

}  // namespace needle_sim
