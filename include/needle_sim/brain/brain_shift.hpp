#pragma once
// The brain-shift pre-step of the DBS scenario (doc/method.md, "Brain shift"): after the burr hole, CSF
// drains and the brain above the CSF level loses its buoyancy. Gravity on that part (or on
// all of the brain) deforms it quasi-statically, held by the clamped regions (brainstem,
// optic nerves) and kept inside the skull.
//
// The skull keeps the brain in (skull_contact.hpp): Newton on the penalised energy, then a
// multiplier update, until the penetration is below the tolerance. After the pre-step, the
// skull's reaction forces are
// kept as constant loads with the shift load, so the shifted brain is the equilibrium the
// insertion starts from. With `skull.support` (default), the skull also keeps holding the
// brain where it touched it: each vertex in contact gets a linear spring along the skull's
// normal (the contact penalty, anchored at its shifted position; it slides freely along
// the skull). Without it the brain hangs from the clamps alone during the insertion and
// swings under the needle's forces.
//
// On an adaptive mesh the pre-step alternates solve, estimate and refine until the mesh
// stops changing (Simulation); rebind() moves the contact to the new mesh with its
// multipliers, and apply() starts from the previous load scale.
//
// With `target_shift`, the load scale is solved for with the displacements under
// displacement control (TissueBody::LoadControl) until the target moves by that distance
// (the paper reproduces a measured shift of about 6.5 mm).

#include <optional>
#include <string>
#include <vector>

#include "needle_sim/brain/brain_shift_settings.hpp"
#include "needle_sim/brain/skull_contact.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/tissue/tissue_body.hpp"
#include "needle_sim/tissue/tissue_parameters.hpp"

namespace needle_sim {

struct BrainShiftResult {
  bool done = false;
  double load_scale = 1;            // factor on the gravity load
  Vec3 target_displacement = Vec3::Zero();
  std::string target;               // "" without a target
  double max_displacement = 0;      // largest nodal displacement [m]
  int load_solves = 0;              // static solves (load steps, then one controlled solve)
  int newton_iterations = 0;
  int multiplier_updates = 0;
  int restarts = 0;                 // first load steps tried again from rest at 1/8 of the load
  int factorizations = 0;
  double factor_ms = 0, solve_ms = 0;
  int passes = 0;                   // solve + adapt passes (1 without adaptivity)
  int dofs = 0;                     // tissue DOFs of the mesh it ended on
  int contacts = 0;                 // surface vertices pressed on the skull at the end
  double max_penetration = 0;       // largest g_v > 0 at the end [m]
  double skull_force = 0;           // |sum of skull reactions| [N]
  double ms = 0;
  // The coarse start (brain_shift.coarse_start), when it ran: its grid's DOFs, its share of
  // the counts and the time above, and the load scale it handed on (0 DOFs: none).
  int coarse_dofs = 0;
  int coarse_newton_iterations = 0, coarse_factorizations = 0;
  double coarse_ms = 0, coarse_load_scale = 0;
};

class BrainShift {
 public:
  // organ: the embedded organ surface (immersed geometry) or nullptr (contact then
  // disabled). target: the tracked material point, or nullptr.
  BrainShift(const BrainShiftSettings& settings, const TissueParameters& tissue, const EmbeddedSurface* organ);

  // Gravity load of the shift at unit scale on `body`'s mesh (3n).
  VecX unitLoad(const TissueBody& body) const;
  // Runs the pre-step on `body`, which ends at equilibrium with the shift load and the
  // frozen skull reactions applied. Throws NumericalError when it fails to converge or the
  // target shift cannot be reached.
  // start_scale: the load scale of the first solve (the previous pass's on a refined mesh).
  // rough: solves to a loose tolerance, target_shift to 1 % (a pass of the adaptive
  // pre-step whose state only feeds the error estimate and the next pass's scale).
  // calibrate: false skips target_shift (one solve at start_scale).
  BrainShiftResult apply(TissueBody& body, const EmbeddedPoint* target, double start_scale = 1.0, bool rough = false,
                         bool calibrate = true);
  // The organ surface embedded in a new mesh (same vertices): contact state carried over.
  void rebind(const EmbeddedSurface* organ) {
    organ_ = organ;
    if (skull_ && organ) skull_->rebind(*organ);
  }
  // Skull reaction per organ-surface vertex at the end of apply() (empty without contact).
  const std::vector<Vec3>& skullForces() const;
  // The frozen skull reactions as nodal forces on a (possibly new) mesh.
  VecX skullLoad(const TissueBody& body, const EmbeddedSurface& organ) const;
  // The skull support springs (see above) on a (possibly new) mesh: their stiffness blocks
  // and the constant force of their anchors, so that their force is anchorLoad - K_s x.
  ElementBlocks supportStiffness(const EmbeddedSurface& organ) const;
  VecX supportAnchorLoad(const TissueBody& body, const EmbeddedSurface& organ) const;
  bool hasSupport() const { return settings_.skull_support && skull_ && skull_->touching(); }
  // After the pre-step, the loads that outlive a mesh change, applied to `body` on any mesh
  // (organ: the organ surface embedded in it, or nullptr): the shift's gravity at load_scale
  // and the frozen skull reactions (shiftLoad), times `factor` (an adopted stiffness's:
  // AdaptiveTissue::setPersistentLoads), and the support springs. Reads the frozen state
  // only: callable from any thread (a mesh change built in the background).
  void applyPersistentLoads(TissueBody& body, const EmbeddedSurface* organ, double load_scale,
                            double factor = 1.0) const;
  // The shift's gravity at load_scale plus the frozen skull reactions, on body's mesh.
  VecX shiftLoad(const TissueBody& body, const EmbeddedSurface* organ, double load_scale) const;
  // The support springs alone (hasSupport), on `body`.
  void applySupport(TissueBody& body, const EmbeddedSurface* organ) const;

 private:
  BrainShiftSettings settings_;
  double density_;
  const EmbeddedSurface* organ_;
  std::optional<SkullContact> skull_;  // with an organ surface and skull contact
};

}  // namespace needle_sim
