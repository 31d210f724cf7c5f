#include "needle_sim/sim/live_loop.hpp"

namespace needle_sim {

void applyLiveLoop(Scene& scene, const LiveLoopOptions& o) {
  if (!o.deterministic_factor) scene.solver.linear.async_lag = 0;
  // The brain (Poisson 0.4977, bulk modulus 220 times the shear's) took 4-18 CG iterations a
  // step on a factor a few steps old, and 206 of 1,800 paced steps over dt, against 4 with
  // lagged rotations; the phantom (0.4) and the gel (0.475) converge in 1-3 anyway and would
  // only pay the refreshes (doc/method.md "Time integration").
  if (o.rotation_drift >= 0) scene.solver.linear.rotation_drift = o.rotation_drift;
  else if (scene.solver.linear.rotation_drift == 0 && scene.tissue.material.poisson >= kNearlyIncompressible)
    scene.solver.linear.rotation_drift = kLiveRotationDrift;
}

}  // namespace needle_sim
