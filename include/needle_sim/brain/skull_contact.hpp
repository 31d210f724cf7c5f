#pragma once
// The skull holding the brain in the brain-shift pre-step (doc/method.md, "Brain shift"):
// unilateral contact between the embedded organ-surface vertices and either the undeformed
// surface offset outwards by `gap` or a rigid skull surface, both taken as the tangent
// plane at the vertex's rest position (displacements of millimetres against curvature radii
// of centimetres):
//     g_v(x) = n_v . (p_v(x) - X_v) - c_v <= 0,    p_v = sum_a w_a x_a,
// solved by an augmented Lagrangian (penalty k_v, multipliers lambda_v >= 0 updated as
// lambda_v <- max(0, lambda_v + k_v g_v)). At the end of the pre-step its reactions are
// frozen as loads, and the vertices in contact keep a spring along the skull's normal
// anchored where they are (the support during the insertion).
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"
#include "needle_sim/solver/system_solver.hpp"

namespace needle_sim {

class SkullContact {
 public:
  // skull: a rigid skull surface, or nullptr for the undeformed surface offset by gap.
  // stiffness: the tissue's Young's modulus (the penalty's scale).
  SkullContact(const EmbeddedSurface& organ, const TriangleMesh* skull, double gap, double stiffness);
  // The organ surface embedded in a new mesh (same vertices): the contact state carries over.
  void rebind(const EmbeddedSurface& organ) { organ_ = &organ; }
  // Gaps are measured from the vertices' interpolated rest positions on this mesh, so that
  // g is exactly -c at rest.
  void setRest(const HexMesh& mesh);
  int numVertices() const { return static_cast<int>(lambda_.size()); }

  // g_v at positions x.
  double gap(int v, const HexMesh& mesh, const VecX& x) const;
  // Augmented-Lagrangian contact force (added to f, 3n) and its stiffness blocks.
  void addForces(const HexMesh& mesh, const VecX& x, VecX& f, ElementBlocks& K) const;
  // Largest g_v, and the number of vertices whose force is on.
  double penetration(const HexMesh& mesh, const VecX& x, int& active) const;
  void updateMultipliers(const HexMesh& mesh, const VecX& x);
  // The largest a in (0, 1] such that x + a dx presses no vertex that is off at x more than
  // `depth` beyond the skull (at least min_step).
  double stepLimit(const HexMesh& mesh, const VecX& x, const VecX& dx, double depth, double min_step) const;

  // Freezes the reactions at x: returns their nodal force (to be kept as a load) and
  // records the vertices in contact and their positions (the support's anchors).
  VecX freeze(const HexMesh& mesh, const VecX& x, Vec3& total);
  const std::vector<Vec3>& reactions() const { return reaction_; }
  // The frozen reactions as nodal forces on a (possibly new) mesh.
  VecX frozenLoad(const HexMesh& mesh, const EmbeddedSurface& organ) const;
  // The support springs on a (possibly new) mesh: stiffness blocks, and the constant force
  // of their anchors (their force is anchorLoad - K_s x).
  bool touching() const { return !anchor_.empty(); }
  ElementBlocks supportStiffness(const EmbeddedSurface& organ) const;
  VecX supportAnchorLoad(const HexMesh& mesh, const EmbeddedSurface& organ) const;
  // Size of the grid's first cell (the length scale of the penalty and tolerances).
  static double cellSize(const HexMesh& mesh);

 private:
  const EmbeddedSurface* organ_;
  std::vector<Vec3> normal_;    // outward unit normal per vertex (rest)
  std::vector<Vec3> rest_;      // interpolated rest position per vertex
  std::vector<double> offset_;  // c_v
  std::vector<double> k_;       // penalty per vertex
  std::vector<double> lambda_;  // multipliers
  std::vector<Vec3> reaction_;  // frozen reactions per vertex
  std::vector<int> touching_;   // vertices in contact when frozen
  std::vector<Vec3> anchor_;    // their positions then
};

}  // namespace needle_sim
