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
  // A new shaft point's or the tip's new element's compliance columns, solved on the stepping
  // thread when it meets them, made DBS steps of 7-12 ms (24 columns and 8 stale ones on
  // 5,295 DOFs); the refreshes compute them beforehand. Where the rotations lag too: there the
  // refreshes come regularly and the mesh is large. The adaptive phantom (1 ms steps, its mesh
  // changes built in 30 ms) had 1.2 and 3.2 % of its steps late with them, 0.10 and 0.35 %
  // without.
  scene.solver.linear.columns_ahead = scene.solver.linear.rotation_drift > 0;
  // Goal-oriented passes (a factorisation of K each: 25-60 ms on dbs_goal's 5,295 DOFs, steps
  // of 30-140 ms on the stepping thread) run in the background, decided at the step their mesh
  // change switches at, when the scene defers its mesh changes and sets no estimate_delay.
  if (scene.adaptivity && scene.adaptivity->estimator == AdaptivitySettings::Estimator::Goal &&
      scene.adaptivity->estimate_delay == 0 && scene.adaptivity->rebuild_delay > 0)
    scene.adaptivity->estimate_delay = scene.adaptivity->rebuild_delay;
}

}  // namespace needle_sim
