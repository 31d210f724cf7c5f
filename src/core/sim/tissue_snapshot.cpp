#include "needle_sim/sim/tissue_snapshot.hpp"

#include <algorithm>

#include "needle_sim/fem/corotational_hex_model.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

TissueSnapshot SnapshotTaker::take(const Simulation& sim, bool with_estimate, bool with_organ) {
  TissueSnapshot s;
  if (!sim.hasTissue()) return s;
  const TissueBody& t = sim.tissue();
  const HexMesh& mesh = t.mesh();
  if (!mesh_ || source_ != &mesh || source_elements_ != mesh.numElements() || source_nodes_ != mesh.numNodes()) {
    mesh_ = std::make_shared<const HexMesh>(mesh);
    source_ = &mesh;
    source_elements_ = mesh.numElements();
    source_nodes_ = mesh.numNodes();
  }
  s.mesh = mesh_;
  s.material = t.model().materialInUse();  // with an adopted stiffness
  s.x = t.positions();
  if (const VecX* r = sim.estimateReference()) s.reference = *r;
  s.level = sim.elementLevels();
  if (with_estimate)
    if (const ErrorEstimate* e = sim.currentEstimate()) s.estimate = std::make_shared<const ErrorEstimate>(*e);
  if (with_organ)
    if (const EmbeddedSurface* organ = sim.organSurface()) {
      s.organ = organ->restPtr();
      organ->positions(s.x, s.organ_positions);
    }
  return s;
}

DisplayFields DisplayFieldBuilder::build(const TissueSnapshot& s, bool errors, bool surface) {
  DisplayFields f;
  if (!s.mesh) return f;
  const HexMesh& mesh = *s.mesh;
  if (mesh_ != s.mesh) {  // a new mesh: its model and estimator (once per mesh change)
    estimator_.reset();
    model_ = std::make_unique<CorotationalHexModel>(mesh, s.material);
    estimator_ = std::make_unique<SprEstimator>(*model_);
    faces_ = mesh.boundaryFaces();
    mesh_ = s.mesh;
  }
  model_->setStiffnessScale(s.material.young / model_->material().young);  // adopted since
  f.u = s.x - mesh.restPositions();
  const int ne = mesh.numElements(), nn = mesh.numNodes();
  if (errors) {
    ErrorEstimate own;
    const ErrorEstimate* est = s.estimate.get();
    if (!est) {
      own = estimator_->estimate(s.x, s.reference.size() ? &s.reference : nullptr);
      est = &own;
    }
    f.von_mises.assign(nn, 0.f);
    f.eta.assign(nn, 0.f);
    std::vector<int> count(nn, 0);
    f.centroid.resize(ne);
    f.extent.resize(ne);
    f.element_eta = est->eta;
    f.eta_max = est->max;
    f.level = s.level;
    for (int e = 0; e < ne; ++e) {
      const double vm = SprEstimator::vonMises(est->centroid_stress[e]);
      Vec3 c = Vec3::Zero();
      for (int a : mesh.element(e)) {
        f.von_mises[a] += static_cast<float>(vm);
        f.eta[a] += static_cast<float>(est->eta[e]);
        ++count[a];
        c += s.x.segment<3>(3 * a) / 8.0;
      }
      f.centroid[e] = c;
      const auto X = mesh.elementCorners(e);
      f.extent[e] = X.colwise().maxCoeff() - X.colwise().minCoeff();
    }
    for (int a = 0; a < nn; ++a)
      if (count[a]) f.von_mises[a] /= count[a], f.eta[a] /= count[a];
  }
  if (surface) {
    if (s.organ) {
      const TriangleMesh& rest = *s.organ;
      for (int tr = 0; tr < rest.numTriangles(); ++tr)
        for (int v : rest.triangle(tr)) {
          f.corners.push_back(s.organ_positions[v]);
          f.corner_u.push_back((s.organ_positions[v] - rest.vertex(v)).norm());
        }
    } else {
      for (const auto& face : faces_)
        for (int k : {0, 1, 2, 0, 2, 3}) {
          const int n = face.nodes[k];
          f.corners.push_back(s.x.segment<3>(3 * n));
          f.corner_u.push_back(f.u.segment<3>(3 * n).norm());
        }
    }
  }
  return f;
}

}  // namespace needle_sim
