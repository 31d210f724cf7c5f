#include "needle_sim/tissue/tissue_loads.hpp"

#include <cmath>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

namespace {
double regionTolerance(const HexMesh& mesh) { return 1e-8 * (mesh.boundsMax() - mesh.boundsMin()).norm(); }
}  // namespace

std::vector<char> prescribeDirichlet(const HexMesh& mesh, const std::vector<DirichletCondition>& conditions,
                                     const std::string& source, VecX& x) {
  const int n = mesh.numNodes();
  const double tol = regionTolerance(mesh);
  std::vector<char> prescribed(3 * n, 0);
  for (size_t k = 0; k < conditions.size(); ++k) {
    const DirichletCondition& dc = conditions[k];
    int count = 0;
    for (int i = 0; i < n; ++i)
      if (dc.region.contains(mesh.node(i), tol)) {
        ++count;
        for (int d = 0; d < 3; ++d)
          if (dc.components[d]) {
            prescribed[3 * i + d] = 1;
            x[3 * i + d] = mesh.node(i)[d] + dc.displacement[d];
          }
      }
    if (count == 0) throw InputError(source, "dirichlet[" + std::to_string(k) + "].region", "selects no grid node of the tissue");
  }
  return prescribed;
}

void addFaceTraction(const HexMesh& mesh, const BoundaryFace& f, const Vec3& t, VecX& out) {
  const double g = 1.0 / std::sqrt(3.0);
  static const double sgn[4][2] = {{-1, -1}, {1, -1}, {1, 1}, {-1, 1}};
  for (int i = 0; i < 4; ++i) {
    const double s = sgn[i][0] * g, r = sgn[i][1] * g;
    Vec3 ds = Vec3::Zero(), dr = Vec3::Zero();
    double N[4];
    for (int q = 0; q < 4; ++q) {
      N[q] = 0.25 * (1 + sgn[q][0] * s) * (1 + sgn[q][1] * r);
      ds += 0.25 * sgn[q][0] * (1 + sgn[q][1] * r) * mesh.node(f.nodes[q]);
      dr += 0.25 * sgn[q][1] * (1 + sgn[q][0] * s) * mesh.node(f.nodes[q]);
    }
    const double dA = ds.cross(dr).norm();
    for (int q = 0; q < 4; ++q) node3(out, f.nodes[q]) += t * (N[q] * dA);
  }
}

VecX tissueLoads(const HexMesh& mesh, const VecX& vol, const TissueParameters& p, const std::string& source) {
  const int n = mesh.numNodes();
  VecX f = VecX::Zero(3 * n);
  const double rho = p.material.density;
  for (int i = 0; i < n; ++i) node3(f, i) = vol[i] * (rho * p.gravity + p.body_force);
  if (p.tractions.empty()) return f;
  const double tol = regionTolerance(mesh);
  const auto faces = mesh.boundaryFaces();
  for (size_t k = 0; k < p.tractions.size(); ++k) {
    const TractionLoad& tl = p.tractions[k];
    int count = 0;
    for (const auto& face : faces) {
      bool inside = true;
      for (int q : face.nodes) inside = inside && tl.region.contains(mesh.node(q), tol);
      if (!inside) continue;
      ++count;
      addFaceTraction(mesh, face, tl.traction, f);
    }
    if (count == 0) throw InputError(source, "tractions[" + std::to_string(k) + "].region", "contains no boundary face of the tissue");
  }
  return f;
}

}  // namespace needle_sim
