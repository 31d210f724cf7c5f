#pragma once
// The check every scene passes, loaded from a file or built in code: each section's values
// against their declarations (core/parameters.hpp: ranges, choices), and the rules that tie
// keys or sections together (an inner radius below the outer one, a bevel needing an
// interaction, the coarsening threshold below half the marking one, a shift target that
// exists, ...). Throws InputError(file, key, problem) naming the first offending key.
#include <string>
#include <vector>

#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

void checkScene(const Scene& scene);

// What a valid scene may still get wrong, one sentence each for its user (the tool prints them
// on stderr, the node logs them as warnings): trilinear hexahedra at nu >= 0.45, where they
// lock volumetrically (doc/method.md "Tissue").
std::vector<std::string> sceneWarnings(const Scene& scene);

// The nu from which the trilinear element's volumetric locking is worth a warning: on the
// paper's block under gravity (8x4x4) it is 15 % stiffer than the continuum at 0.45 and 74 % at
// 0.4999 (doc/verification.md "Nearly incompressible tissue").
constexpr double kTrilinearLockingPoisson = 0.45;

}  // namespace needle_sim
