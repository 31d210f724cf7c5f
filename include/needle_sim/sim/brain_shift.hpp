#pragma once
// The brain-shift pre-step of the DBS scenario (DESIGN.md §4): after the burr hole, CSF
// drains and the brain above the CSF level loses its buoyancy. Gravity on that part (or on
// all of the brain) deforms it quasi-statically, held by the clamped regions (brainstem,
// optic nerves) and kept inside the skull.
//
// Skull contact is unilateral, between the embedded organ-surface vertices and either the
// undeformed surface offset outwards by `gap` or a rigid skull surface; both are taken as
// the tangent plane at the vertex's rest position (displacements of millimetres against
// curvature radii of centimetres):
//     g_v(x) = n_v . (p_v(x) - X_v) - c_v <= 0,    p_v = sum_a w_a x_a.
// It is solved by an augmented Lagrangian: Newton on the penalised energy with
// multipliers lambda_v >= 0, then lambda_v <- max(0, lambda_v + k_v g_v), until the
// penetration is below the tolerance. After the pre-step, the skull's reaction forces are
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
#include <vector>

#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/tissue_body.hpp"

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
  int factorizations = 0;
  double factor_ms = 0, solve_ms = 0;
  int passes = 0;                   // solve + adapt passes (1 without adaptivity)
  int dofs = 0;                     // tissue DOFs of the mesh it ended on
  int contacts = 0;                 // surface vertices pressed on the skull at the end
  double max_penetration = 0;       // largest g_v > 0 at the end [m]
  double skull_force = 0;           // |sum of skull reactions| [N]
  double ms = 0;
};

class BrainShift {
 public:
  // organ: the embedded organ surface (immersed geometry) or nullptr (contact then
  // disabled). target: the tracked material point, or nullptr.
  BrainShift(const BrainShiftScene& scene, const TissueScene& tissue, const EmbeddedSurface* organ);

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
  void rebind(const EmbeddedSurface* organ) { organ_ = organ; }
  // Skull reaction per organ-surface vertex at the end of apply() (zero without contact).
  const std::vector<Vec3>& skullForces() const { return skull_force_; }
  // The frozen skull reactions as nodal forces on a (possibly new) mesh.
  VecX skullLoad(const TissueBody& body, const EmbeddedSurface& organ) const;
  // The skull support springs (see above) on a (possibly new) mesh: their stiffness blocks
  // and the constant force of their anchors, so that their force is anchorLoad - K_s x.
  ElementBlocks supportStiffness(const EmbeddedSurface& organ) const;
  VecX supportAnchorLoad(const TissueBody& body, const EmbeddedSurface& organ) const;
  bool hasSupport() const { return scene_.skull_support && !anchor_.empty(); }

 private:
  void contact(const TissueBody& body, const VecX& x, VecX& f, ElementBlocks& K) const;
  double penetration(const TissueBody& body, int& active) const;

  BrainShiftScene scene_;
  double density_;
  const EmbeddedSurface* organ_;
  std::vector<Vec3> normal_;      // outward unit normal per vertex (rest)
  std::vector<Vec3> rest_;        // interpolated rest position per vertex
  std::vector<double> offset_;    // c_v
  std::vector<double> k_;         // penalty per vertex
  std::vector<double> lambda_;    // multipliers
  std::vector<Vec3> skull_force_;
  std::vector<int> touching_;     // vertices in contact at the end of apply()
  std::vector<Vec3> anchor_;      // their shifted positions
};

}  // namespace needle_sim
