#pragma once
// How a live loop runs a scene, where it differs from the CLI (doc/ros_api.md,
// ~deterministic_factor and ~rotation_drift): the node applies it to the scene it loads, and
// `needle_sim check` to the scene its pre-flight times, so that both state the real time of the
// same loop.
//   - A factor refreshed in the background is swapped in as soon as it is ready
//     (solver.linear.async_lag 0: no step waits for it), unless deterministic.
//   - Lagged rotations (solver.linear.rotation_drift, doc/method.md "Time integration") where a
//     stale factor costs most: nearly incompressible tissue.
//   - The compliance columns ahead of the needles computed by the refreshes
//     (solver.linear.columns_ahead) where the rotations lag.
//   - Goal-oriented passes in the background (adaptivity.estimate_delay = rebuild_delay where
//     the scene sets none).
#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

// The automatic choice: lagged rotations of this angle [rad] for tissue whose Poisson ratio is
// at least kNearlyIncompressible (bulk modulus 50 times the shear modulus and more).
constexpr double kLiveRotationDrift = 0.01;
constexpr double kNearlyIncompressible = 0.49;

struct LiveLoopOptions {
  bool deterministic_factor = false;  // keep the scene's async_lag
  // >= 0: the scene's solver.linear.rotation_drift becomes this; < 0: the scene's if it sets
  // one, else kLiveRotationDrift for nearly incompressible tissue.
  double rotation_drift = -1;
};

void applyLiveLoop(Scene& scene, const LiveLoopOptions& o = {});

}  // namespace needle_sim
