#pragma once
// Needle-tissue interaction (paper §2.1 and §2.4, doc/method.md "Needle-tissue
// constraints"): the insertion state machine of each needle, the creation and release of
// the three constraint kinds as the needle is inserted and withdrawn, and the constraint
// solve. Its pieces: the needle's centre line (centre_line.hpp), needles in needles
// (sheath.hpp), the rows and the Delassus operator (constraint_rows.hpp), the laws
// (puncture/tip/shaft_constraint.hpp), projected Gauss-Seidel (projected_gauss_seidel.hpp).
//
// Per step, between the bodies' free motion and their commit:
//   1. detect the tip meeting the surface (approaching needles), update every constraint's
//      frame and gap at the current positions, release shaft points the needle has left;
//   2. rows H: each point touches 8 tissue nodes (trilinear weights) and 2 needle nodes;
//   3. compliance W = h (H_T A_T^-1 H_T^T + H_N A_N^-1 H_N^T) from each body's factor, with
//      one multi-right-hand-side solve over the DOFs the rows touch;
//   4. projected Gauss-Seidel with the laws; 5. corrections dv += h A^-1 H^T lambda.
// After the commit, the laws' state changes: puncture when the normal force exceeds the
// puncture strength, cutting (the tip anchor moves, shaft points are laid every
// shaft_spacing along the cut path), withdrawal (tip released, shaft points only).
// A step with no constraint costs one surface test per approaching needle.
//
// Several needles (cannula + electrode): a needle whose tip lies inside another needle's
// lumen touches no tissue; shaft points released by a withdrawing needle pass to another
// needle that runs through them; a needle whose tip comes out of its sheath inside the
// tissue is tied there by a tip constraint (the electrode left in place). The electrode is
// not coupled laterally to the cannula while inside it.
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/contact/constraint_rows.hpp"
#include "needle_sim/contact/contact_constraint.hpp"
#include "needle_sim/contact/interaction_settings.hpp"
#include "needle_sim/contact/tip_constraint.hpp"
#include "needle_sim/contact/tissue_surface.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

enum class InsertionState { Approaching, InContact, Punctured, Inserted, Withdrawing, Out };
const char* toString(InsertionState s);

struct InteractionStats {
  int points = 0;
  int iterations = 0;
  double residual = 0;
  bool converged = true;
  double ms = 0;  // whole constraint phase
};

// What the interaction looks up on a tissue mesh (its surface, a locator by rest position,
// the elements around each node): it depends on the mesh only, so a mesh change builds it
// with the new body, off the stepping thread (AdaptiveTissue::prepare), and the switch
// only takes it (rebind).
struct TissueBinding {
  std::unique_ptr<TissueSurface> surface;
  std::unique_ptr<PointLocator> locator;
  std::vector<std::vector<int>> node_elements;
  // For `mesh` (which must outlive it), with `organ` the embedded organ surface or nullptr.
  static TissueBinding make(const HexMesh& mesh, const EmbeddedSurface* organ);
};

class NeedleTissueInteraction {
 public:
  // `organ`: the embedded organ surface of immersed geometry (the needle punctures it
  // rather than the grid's boundary); nullptr for a meshed body. It must outlive the
  // binding (rebind with the new one after a mesh change).
  NeedleTissueInteraction(const InteractionSettings& settings, TissueBody& tissue, std::vector<NeedleBody*> needles,
                          const EmbeddedSurface* organ = nullptr);

  // A copy of other's constraints and insertion states acting on copies of its bodies
  // (tissue on the same mesh, needles in the same order).
  NeedleTissueInteraction(const NeedleTissueInteraction& other, TissueBody& tissue, std::vector<NeedleBody*> needles,
                          const EmbeddedSurface* organ = nullptr);
  NeedleTissueInteraction(const NeedleTissueInteraction&) = delete;
  NeedleTissueInteraction& operator=(const NeedleTissueInteraction&) = delete;
  // Between the bodies' freeMotion and commit.
  InteractionStats solve(double h);
  // After the bodies' commit: puncture, cutting, withdrawal.
  void afterCommit();
  // The tissue body was rebuilt on a refined or coarsened mesh: every constraint point is
  // re-embedded by its rest position, the surface and locators are rebuilt.
  void rebind(TissueBody& tissue, const EmbeddedSurface* organ = nullptr);
  // The same with the binding of tissue's mesh made beforehand (TissueBinding::make).
  void rebind(TissueBody& tissue, TissueBinding binding);

  InsertionState state(int needle) const { return tracks_[needle].state; }
  // How far the needle's base has moved back along its axis since its tip was released
  // (Withdrawing), [m]; 0 in any other state. A needle whose tip backs off by micrometres
  // while its base holds still (an electrode left in place as the cannula is withdrawn) has
  // not been withdrawn: observables.hpp reports it inserted.
  double withdrawnSinceRelease(int needle) const;
  int activePoints(int needle) const;
  const std::vector<std::unique_ptr<ContactConstraint>>& constraints() const { return constraints_; }
  // Normal force at the moment of the last puncture of a needle (NaN before any).
  double punctureForce(int needle) const { return tracks_[needle].puncture_force; }
  // The centre line of the needle's cut path in rest (material) space, from the puncture
  // point to the tip's last anchor, a point every quarter shaft spacing (empty before a
  // puncture; a new puncture starts a new one).
  const std::vector<Vec3>& cutPath(int needle) const { return tracks_[needle].path; }
  // Where the next constraint points of each cutting needle will be embedded (rest space): its
  // next shaft point (a straight needle's, exactly where it will be laid) and its tip half and
  // one shaft spacing ahead along the cut path, the first also a quarter spacing off the path
  // in four directions (the tip's material point drifts off the rest path). The tissue body
  // precomputes the compliance columns of their elements (TissueBody::setElementsAhead, bound
  // with the body; a deferred mesh change's new body too: Simulation::constraintPoints).
  std::vector<Vec3> pointsAhead() const;
  std::vector<int> elementsAhead() const;
  // The same path where its material points are now (the deformed tissue), in `out` (a point
  // a rounding error outside the cells after a mesh change is taken in the nearest one).
  void cutPathNow(int needle, std::vector<Vec3>& out) const;
  // Total constraint force on a needle, assembled on its nodes with the rows' weights, and
  // on the tissue (all nodes, prescribed ones included), at the last solve.
  Vec3 forceOnNeedle(int needle) const;
  Vec3 forceOnTissue() const;
  const InteractionSettings& settings() const { return settings_; }
  // New values of puncture_force, cutting_force, friction and grip_pressure during a run (the
  // rest of `s` is ignored), taken by every constraint in place from the next solve: an
  // estimate adopted by the live simulation (Simulation::adopt). A bevel's lateral load
  // keeps its ratio to the cutting force.
  void setValues(const InteractionSettings& s);

 private:
  struct Track {
    InsertionState state = InsertionState::Approaching;
    double puncture_force = std::numeric_limits<double>::quiet_NaN();
    Vec3 next_shaft_rest = Vec3::Zero();  // where the next shaft point goes (rest space)
    bool has_path = false;
    bool sheathed = false;  // the tip is inside another needle's lumen (electrode in cannula)
    // Withdrawing: the end of the cut path (the tip's last anchor). Pushed past it again, the
    // tip meets uncut tissue there and cuts on (a back-and-forth motion, or the tissue
    // relaxing ahead of the tip).
    EmbeddedPoint path_end;
    bool has_end = false;
    Vec3 release_base = Vec3::Zero();  // the base where the tip was released
    std::vector<Vec3> path;  // cutPath()
    // A bevel needle's shaft points go by the length its tip cut (rest space) since the
    // puncture: the next is due at next_shaft_at.
    double cut_length = 0, next_shaft_at = 0;
  };
  std::unique_ptr<TipConstraint> makeTip(int n) const;
  void extendPath(int n, const Vec3& rest);
  bool locateCurrent(const Vec3& p, int hint, EmbeddedPoint& out) const;
  // Appends to `out` (not to constraints_, which the caller may be iterating).
  void layShaftPoints(int n, const EmbeddedPoint& upto, std::vector<std::unique_ptr<ContactConstraint>>& out);
  // Frames, gaps and arc lengths of the points at the current positions; drops points the
  // needle has left. True when a tip lost its surface contact (slid off an edge).
  bool updateGeometry();
  // Contact detection for needle n if it is out of the tissue: a puncture point where its tip
  // meets the surface in this step (h).
  void detect(int n, double h);
  double grip(int n) const;  // shaft points' grip force on needle n [N]
  // A shaft point's lateral compliance [m/N] on needle n in tissue element e
  // (interface_compliance.hpp; 0: rigid).
  double interfaceCompliance(int n, int e) const;
  void bindTissue(TissueBody& tissue, TissueBinding binding);

  InteractionSettings settings_;
  TissueBody* tissue_ = nullptr;
  std::vector<NeedleBody*> needles_;
  std::unique_ptr<TissueSurface> surface_;
  std::unique_ptr<PointLocator> rest_locator_;
  std::vector<std::vector<int>> node_elements_;  // node -> elements
  std::vector<std::unique_ptr<ContactConstraint>> constraints_;
  std::vector<Track> tracks_;
  std::vector<int> column_of_;  // scratch: free tissue DOF -> column in the touched set
};

}  // namespace needle_sim
