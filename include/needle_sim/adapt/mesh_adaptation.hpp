#pragma once
// One adaptation pass (paper §2.3, doc/method.md): from the element error indicators of the
// current mesh, mark (max or bulk rule), refine by the 1 -> 8 template within max_level and
// the DOF budget, merge back children whose error has stayed small (hysteresis), and carry
// nodal fields to the new mesh.
//
// Elements are identified across passes by their forest cell, nodes by their forest id,
// so a field moves to the new mesh by: kept nodes keep their value, new nodes take the
// average of their sources (the parent's trilinear field at that point), nodes that
// became hanging are set by the body from their masters. Refining therefore never moves
// material; coarsening projects onto the coarser space.
#include <memory>
#include <unordered_map>
#include <vector>

#include "needle_sim/adapt/adaptivity_settings.hpp"
#include "needle_sim/adapt/marking.hpp"
#include "needle_sim/adapt/refinable_hex_mesh.hpp"
#include "needle_sim/adapt/spr_estimator.hpp"

namespace needle_sim {

struct AdaptationResult {
  bool changed = false;
  int marked = 0;      // elements marked for refinement
  int ahead = 0;       // of them, marked for lying ahead of a tip (AdaptivitySettings::lookahead)
  int refined = 0;     // cells split, including those the 2:1 balance required
  int coarsened = 0;   // parents whose children were merged back
  bool budget_reached = false;    // max_dofs stopped the refinement
  bool below_tolerance = false;   // the estimate met the tolerance: nothing refined
};

class MeshAdaptation {
 public:
  MeshAdaptation(const AdaptivitySettings& settings, const HexMesh& coarse);
  // A copy with the same forest, active mesh and hysteresis state.
  MeshAdaptation(const MeshAdaptation& other);
  MeshAdaptation& operator=(const MeshAdaptation&) = delete;

  // The current mesh (elements, levels, hanging nodes).
  const RefinableHexMesh::Active& active() const { return active_; }
  const RefinableHexMesh& forest() const { return forest_; }
  const AdaptivitySettings& settings() const { return settings_; }

  // Marks, coarsens and refines for the estimate of the current active mesh (its eta: the
  // element indicators). refine false: only coarsening (a goal-oriented run whose targets
  // meet their tolerance). ahead: rest-configuration points on the tips' paths ahead; the
  // elements holding them are refined to max_level before the marked ones and not merged.
  AdaptationResult adapt(const ErrorEstimate& estimate, bool refine = true, const std::vector<Vec3>& ahead = {});
  // Refines the given active elements (tests, initial refinement), with 2:1 balance.
  AdaptationResult refineElements(const std::vector<int>& elements);
  // Merges the children of the parents of the given active elements (tests).
  AdaptationResult coarsenElements(const std::vector<int>& elements);

  // A nodal field (3 values per node) of the mesh before the last change, carried to the
  // current mesh. Hanging nodes get their parent field's value too (which the hanging
  // constraint reproduces when the field is trilinear on the coarse side).
  VecX transfer(const VecX& previous) const;

  // Indicators at or below this are round-off, however small the largest estimate seen so
  // far (an unloaded body refined ahead of a needle: its field is round-off of the hanging
  // nodes' constraints, which the max rule would otherwise refine).
  void setRoundOff(double eta) { round_off_ = eta; }

  // Makes the current refinement a floor: later passes never merge what is refined now
  // (the mesh the brain shift was computed on carries its preload).
  void keepCurrentRefinement();

  // Active elements per level 0..max_level.
  std::vector<int> elementsPerLevel() const;
  int numDofs() const { return active_.mesh.numDofs(); }

 private:
  void activate();

  AdaptivitySettings settings_;
  std::unique_ptr<Marking> marking_;
  RefinableHexMesh forest_;
  RefinableHexMesh::Active active_;
  std::vector<int> previous_node_id_;      // forest ids of the previous mesh's nodes
  std::unordered_map<int, int> small_for_;  // parent cell -> consecutive passes its children were small
  double eta_scale_ = 0;                    // largest global estimate seen
  double round_off_ = 0;                    // setRoundOff
  std::unordered_map<int, char> kept_;      // parents that may not be merged
  static constexpr double kNoiseFloor = 1e-6;
};

}  // namespace needle_sim
