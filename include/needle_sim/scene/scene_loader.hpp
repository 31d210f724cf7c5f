#pragma once
// Reading and validating scene files.
//
// Everything is checked before any simulation work: unknown keys, missing required keys,
// wrong types, non-finite numbers and non-physical values raise InputError naming the
// file, the key path (e.g. "tissue.material.poisson") and the problem.
//
// Overrides use the same key paths: "tissue.grid.cells=[16,8,8]" or
// "tissue.dirichlet.0.displacement=[0,0,1e-3]"; the value is parsed as YAML, so lists,
// numbers and strings are written as in the file.
#include <string>
#include <vector>

#include "needle_sim/scene/resource_check.hpp"
#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

// Loads a scene file, applies the overrides in order, validates, and returns the scene.
Scene loadScene(const std::string& path, const std::vector<std::string>& overrides = {});
// Same from YAML text (file name used in messages only).
Scene parseScene(const std::string& yaml_text, const std::string& file_label,
                 const std::vector<std::string>& overrides = {});

}  // namespace needle_sim
