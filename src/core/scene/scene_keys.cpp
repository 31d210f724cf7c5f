#include "needle_sim/scene/scene_keys.hpp"

#include <regex>
#include <sstream>

#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

std::vector<SceneSection> sceneSections() {
  return {
      {"time", "include/needle_sim/scene/scene.hpp", Scene::timeParameters().declarations()},
      {"solver", "include/needle_sim/solver/solver_settings.hpp", SolverSettings::parameters().declarations()},
      {"tissue", "include/needle_sim/tissue/tissue_parameters.hpp", TissueParameters::parameters().declarations()},
      {"tissue.grid", "include/needle_sim/geometry/immersed_grid.hpp", ImmersedGridSettings::parameters().declarations()},
      {"needle", "include/needle_sim/needle/needle_parameters.hpp", NeedleParameters::parameters().declarations()},
      {"needle.bevel", "include/needle_sim/needle/needle_parameters.hpp", BevelParameters::parameters().declarations()},
      {"interaction", "include/needle_sim/contact/interaction_settings.hpp", InteractionSettings::parameters().declarations()},
      {"adaptivity", "include/needle_sim/adapt/adaptivity_settings.hpp", AdaptivitySettings::parameters().declarations()},
      {"brain_shift", "include/needle_sim/brain/brain_shift_settings.hpp", BrainShiftSettings::parameters().declarations()},
  };
}

std::optional<ParameterDeclaration> findSceneKey(const std::string& key) {
  // A needle of the list reads as `needle`: needles.1.young, needles[1].young -> needle.young.
  static const std::regex list(R"(^needles(\.\d+|\[\d+\])\.)");
  const std::string k = std::regex_replace(key, list, "needle.");
  const std::vector<SceneSection> sections = sceneSections();
  // The longest section path that prefixes the key (needle.bevel before needle).
  const SceneSection* best = nullptr;
  for (const auto& s : sections)
    if (k.rfind(s.path + ".", 0) == 0 && (!best || s.path.size() > best->path.size())) best = &s;
  if (!best) return std::nullopt;
  const std::string rest = k.substr(best->path.size() + 1);
  for (const auto& d : best->keys)
    if (d.key == rest) return d;
  return std::nullopt;
}

namespace {
std::string cell(const std::string& s) {
  std::string out;
  for (char c : s) out += c == '|' ? std::string("\\|") : std::string(1, c);
  return out;
}
}  // namespace

std::string sceneKeysMarkdown(const SceneSection& section) {
  std::ostringstream o;
  o << "| key | type | default | valid | meaning |\n|---|---|---|---|---|\n";
  for (const auto& d : section.keys) {
    std::string type = d.type();
    if (d.kind == ParameterKind::Choice) {
      type = "";
      for (const auto& c : d.choices) type += (type.empty() ? "`" : " | `") + c + "`";
    }
    if (!d.unit.empty()) type += " [" + d.unit + "]";
    std::string def = d.required ? "required" : d.default_text.empty() ? "–" : "`" + d.default_text + "`";
    std::string valid;
    if (d.kind == ParameterKind::Real || d.kind == ParameterKind::Integer)
      valid = d.range.text().rfind("in ", 0) == 0 ? d.range.text().substr(3) : d.range.text();
    o << "| `" << d.key << "` | " << cell(type) << " | " << def << " | " << cell(valid) << " | " << cell(d.description)
      << " |\n";
  }
  return o.str();
}

}  // namespace needle_sim
