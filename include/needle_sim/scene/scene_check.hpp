#pragma once
// The check every scene passes, loaded from a file or built in code: each section's values
// against their declarations (core/parameters.hpp: ranges, choices), and the rules that tie
// keys or sections together (an inner radius below the outer one, a bevel needing an
// interaction, the coarsening threshold below half the marking one, a shift target that
// exists, ...). Throws InputError(file, key, problem) naming the first offending key.
#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

void checkScene(const Scene& scene);

}  // namespace needle_sim
