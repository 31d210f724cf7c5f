#pragma once
// The brain-shift pre-step's settings (the scene's `brain_shift` section): quasi-static
// gravity on the brain above the CSF level (or all of it), clamps holding, the brain kept
// inside the skull (unilateral contact against the undeformed surface offset outwards by
// `gap`, or against a rigid skull surface), optionally scaled to a prescribed target shift.
#include <memory>
#include <optional>
#include <string>

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
};

}  // namespace needle_sim
