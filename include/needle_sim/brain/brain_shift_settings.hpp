#pragma once
// The brain-shift pre-step's settings (the scene's `brain_shift` section): quasi-static
// gravity on the brain above the CSF level (or all of it), clamps holding, the brain kept
// inside the skull (unilateral contact against the undeformed surface offset outwards by
// `gap`, or against a rigid skull surface), optionally scaled to a prescribed target shift.
#include <memory>
#include <optional>
#include <string>

#include "needle_sim/core/parameters.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

struct BrainShiftSettings {
  Vec3 gravity = Vec3(0, 0, -9.81);
  bool all = true;                      // the load acts on all of the tissue
  Vec3 csf_point = Vec3::Zero();        // else above the plane through this point, normal to gravity
  std::optional<double> density;        // default: the tissue's
  double gap = 0.0;                     // skull offset from the undeformed surface [m]
  std::shared_ptr<const TriangleMesh> skull;  // or a rigid skull surface
  bool skull_contact = true;
  bool skull_support = true;            // the skull keeps holding the brain during the insertion
  std::optional<double> target_shift;   // scale the load so that `target` moves this far [m]
  std::string target;                   // default: the first target
  // Intraoperative re-planning: after the shift every needle's trajectory is re-aimed at
  // the target's shifted position through its entry point (needle/trajectory_replan.hpp).
  bool replan = false;
  int load_steps = 4;
  // On a uniformly refined immersed grid (tissue.grid.refine >= 1, no adaptivity) with a
  // target_shift: solve the shift roughly on the grid one level coarser first, and start the
  // grid's own solve from its state and load scale (nested iteration; doc/method.md "Brain
  // shift").
  bool coarse_start = true;
  double tolerance = 1e-6;              // relative Newton residual per load step

  // The `brain_shift` section's value keys (core/parameters.hpp); csf_level ('all' or a
  // point) and skull.surface are read by the scene loader.
  static const Parameters<BrainShiftSettings>& parameters() {
    using S = BrainShiftSettings;
    static const Parameters<S> p =
        Parameters<S>()
            .vector("gravity", [](S& s) -> Vec3& { return s.gravity; }, "m/s^2",
                    "direction and size of the load, non-zero (supine patient: towards posterior)")
            .optionalReal("density", [](S& s) -> std::optional<double>& { return s.density; }, "kg/m^3",
                          Range::positive(), "of the load (default: the tissue's)")
            .real("skull.gap", [](S& s) -> double& { return s.gap; }, "m", Range::nonNegative(),
                  "skull = the undeformed organ surface offset outwards by this (or `skull.surface`)")
            .flag("skull.enabled", [](S& s) -> bool& { return s.skull_contact; }, "unilateral skull contact during the shift")
            .flag("skull.support", [](S& s) -> bool& { return s.skull_support; },
                  "afterwards the skull keeps holding the brain where it touched it")
            .optionalReal("target_shift", [](S& s) -> std::optional<double>& { return s.target_shift; }, "m",
                          Range::positive(), "scale the load until `target` has moved this far (displacement control)")
            .text("target", [](S& s) -> std::string& { return s.target; }, "the target of `target_shift` and `replan` (default: the first target)")
            .flag("replan", [](S& s) -> bool& { return s.replan; },
                  "intraoperative re-planning: after the shift every needle's trajectory is re-aimed through its entry point so that its planned final tip moves with `target`; needs a needle and a target ([method.md](method.md#brain-shift))")
            .integer("load_steps", [](S& s) -> int& { return s.load_steps; }, Range::closed(1, 1000),
                     "load steps from rest")
            .flag("coarse_start", [](S& s) -> bool& { return s.coarse_start; },
                  "on a uniformly refined immersed grid (`tissue.grid.refine` ≥ 1, no adaptivity) with `target_shift`: solve the shift roughly on the grid one level coarser first and start from its state and load scale ([method.md](method.md#brain-shift))")
            .real("tolerance", [](S& s) -> double& { return s.tolerance; }, "", Range::open(0, 1),
                  "relative Newton residual");
    return p;
  }
};

}  // namespace needle_sim
