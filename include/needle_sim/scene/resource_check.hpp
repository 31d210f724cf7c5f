#pragma once
// Refusing a scene this machine cannot run, before any work: the memory a uniform grid's
// direct solver would need, estimated from its size.
#include <string>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

// Estimated bytes of the factorisation and its data for a grid of `cells`.
double estimateSolverBytes(const Vec3i& cells);
// Throws InputError(file, key) when the estimate exceeds 60 % of the machine's memory.
void checkSolverMemory(const Vec3i& cells, const std::string& file, const std::string& key);

}  // namespace needle_sim
