#pragma once
// What a viewer shows of the tissue: a snapshot taken at a step boundary (cheap: positions,
// the mesh they belong to, shared until it changes, the estimate if the step made one) and
// its display fields, evaluated later and elsewhere (the node's output thread), so that
// building a picture never delays a step. The fields come from the core's own estimator:
// the simulation's estimate of that state when it has one (adaptive runs), else an SPR
// estimate of the snapshot (the display asked for it).
#include <memory>
#include <vector>

#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/fem/material.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

class Simulation;

struct TissueSnapshot {
  std::shared_ptr<const HexMesh> mesh;
  LinearElasticMaterial material;
  VecX x;          // positions (3n)
  VecX reference;  // the state the estimate measures the change from (empty: rest)
  std::vector<int> level;
  std::shared_ptr<const ErrorEstimate> estimate;  // the simulation's, for this state (or null)
  std::shared_ptr<const TriangleMesh> organ;      // immersed organ surface (or null) ...
  std::vector<Vec3> organ_positions;              // ... and its vertices now
};

// Takes snapshots of one simulation; the mesh is copied only when it changed.
class SnapshotTaker {
 public:
  // with_estimate: the caller will need the error field (copy the simulation's estimate).
  TissueSnapshot take(const Simulation& sim, bool with_estimate, bool with_organ);

 private:
  std::shared_ptr<const HexMesh> mesh_;
  const HexMesh* source_ = nullptr;
  int source_elements_ = -1, source_nodes_ = -1;
};

struct DisplayFields {
  // Per node: displacement (3n), and the average over its elements of the centroid von Mises
  // stress [Pa] and of the error indicator eta.
  VecX u;
  std::vector<float> von_mises, eta;
  // Per element: centroid (current), rest extent, eta, level; the largest eta.
  std::vector<Vec3> centroid, extent;
  std::vector<double> element_eta;
  std::vector<int> level;
  double eta_max = 0;
  // The surface a viewer draws (the organ's, else the mesh boundary: two triangles per face):
  // triangle corners and their displacement magnitude.
  std::vector<Vec3> corners;
  std::vector<double> corner_u;
};

// Evaluates display fields; keeps a model and an estimator of the last mesh it saw.
class DisplayFieldBuilder {
 public:
  DisplayFields build(const TissueSnapshot& s, bool errors, bool surface);

 private:
  std::shared_ptr<const HexMesh> mesh_;
  std::unique_ptr<class CorotationalHexModel> model_;
  std::unique_ptr<SprEstimator> estimator_;
  std::vector<BoundaryFace> faces_;
};

}  // namespace needle_sim
