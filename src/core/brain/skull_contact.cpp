#include "needle_sim/brain/skull_contact.hpp"

#include <algorithm>
#include <cmath>
#include <map>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

namespace {
// Penalty per unit area, in units of (tissue E / cell size). Larger needs fewer multiplier
// updates but more Newton iterations as contacts switch; 3e3 was fastest on the DBS scene.
constexpr double kPenalty = 3e3;

// Adds the stiffness w_a w_c S of a spring S at an embedded point to its element's block.
void addVertexBlock(const EmbeddedPoint& ep, const Mat3& S, std::map<int, size_t>& slot, ElementBlocks& K) {
  auto it = slot.find(ep.element);
  if (it == slot.end()) {
    it = slot.emplace(ep.element, K.element.size()).first;
    K.element.push_back(ep.element);
    K.K.push_back(hex8::Mat24::Zero());
  }
  hex8::Mat24& B = K.K[it->second];
  for (int a = 0; a < 8; ++a)
    for (int c = 0; c < 8; ++c) B.block<3, 3>(3 * a, 3 * c) += ep.weights[a] * ep.weights[c] * S;
}

// Adds a force at an embedded point to the nodes of its element.
void addPointForce(const HexMesh& mesh, const EmbeddedPoint& ep, const Vec3& force, VecX& f) {
  const auto& el = mesh.element(ep.element);
  for (int a = 0; a < 8; ++a) node3(f, el[a]) += ep.weights[a] * force;
}
}  // namespace

double SkullContact::cellSize(const HexMesh& mesh) {
  const Eigen::Matrix<double, 8, 3> X = mesh.elementCorners(0);
  return (X.colwise().maxCoeff() - X.colwise().minCoeff()).maxCoeff();
}

SkullContact::SkullContact(const EmbeddedSurface& organ, const TriangleMesh* skull, double gap, double stiffness)
    : organ_(&organ) {
  const TriangleMesh& m = organ.rest();
  std::vector<double> area;
  m.vertexNormals(normal_, area);
  offset_.assign(m.numVertices(), gap);
  if (skull) {
    // The skull's tangent plane nearest each vertex: normal from the vertex to the skull.
    for (int v = 0; v < m.numVertices(); ++v) {
      const Vec3& X = m.vertex(v);
      double best = 1e300;
      Vec3 q = X;
      for (int t = 0; t < skull->numTriangles(); ++t) {
        const auto& tr = skull->triangle(t);
        const Vec3 c = closestPointOnTriangle(X, skull->vertex(tr[0]), skull->vertex(tr[1]), skull->vertex(tr[2]));
        const double d = (c - X).squaredNorm();
        if (d < best) {
          best = d;
          q = c;
        }
      }
      const double d = std::sqrt(best);
      if (d > 1e-12) normal_[v] = (q - X) / d;
      offset_[v] = d;
    }
  }
  // Penalty ~ kPenalty x the stiffness of a cell of tissue per unit area of surface: large
  // enough for the multiplier updates to converge in a few passes, small enough for Newton.
  const double cell = cellSize(organ.mesh());
  k_.resize(m.numVertices());
  for (int v = 0; v < m.numVertices(); ++v) k_[v] = kPenalty * stiffness / cell * area[v];
  lambda_.assign(m.numVertices(), 0.0);
  reaction_.assign(m.numVertices(), Vec3::Zero());
}

void SkullContact::setRest(const HexMesh& mesh) {
  const VecX X = mesh.restPositions();
  rest_.resize(lambda_.size());
  for (size_t v = 0; v < lambda_.size(); ++v) rest_[v] = organ_->vertex(static_cast<int>(v)).interpolate(mesh, X);
}

double SkullContact::gap(int v, const HexMesh& mesh, const VecX& x) const {
  return normal_[v].dot(organ_->vertex(v).interpolate(mesh, x) - rest_[v]) - offset_[v];
}

void SkullContact::addForces(const HexMesh& mesh, const VecX& x, VecX& f, ElementBlocks& K) const {
  std::map<int, size_t> slot;
  for (int v = 0; v < numVertices(); ++v) {
    const double l = lambda_[v] + k_[v] * gap(v, mesh, x);
    if (l <= 0) continue;
    const EmbeddedPoint& ep = organ_->vertex(v);
    addPointForce(mesh, ep, -l * normal_[v], f);
    addVertexBlock(ep, k_[v] * normal_[v] * normal_[v].transpose(), slot, K);
  }
}

double SkullContact::penetration(const HexMesh& mesh, const VecX& x, int& active) const {
  double worst = 0;
  active = 0;
  for (int v = 0; v < numVertices(); ++v) {
    const double g = gap(v, mesh, x);
    worst = std::max(worst, g);
    active += lambda_[v] + k_[v] * g > 0;
  }
  return worst;
}

double SkullContact::stepLimit(const HexMesh& mesh, const VecX& x, const VecX& dx, double depth, double min_step) const {
  double a = 1;
  for (int v = 0; v < numVertices(); ++v) {
    const double g0 = gap(v, mesh, x);
    if (lambda_[v] + k_[v] * g0 > 0) continue;  // on: the tangent holds it
    const double dg = normal_[v].dot(organ_->vertex(v).interpolate(mesh, dx));
    if (g0 + dg > depth) a = std::min(a, (depth - g0) / dg);
  }
  return std::max(a, min_step);
}

void SkullContact::updateMultipliers(const HexMesh& mesh, const VecX& x) {
  for (int v = 0; v < numVertices(); ++v) lambda_[v] = std::max(0.0, lambda_[v] + k_[v] * gap(v, mesh, x));
}

VecX SkullContact::freeze(const HexMesh& mesh, const VecX& x, Vec3& total) {
  VecX f = VecX::Zero(mesh.numDofs());
  total.setZero();
  touching_.clear();
  anchor_.clear();
  for (int v = 0; v < numVertices(); ++v) {
    const double l = std::max(0.0, lambda_[v] + k_[v] * gap(v, mesh, x));
    reaction_[v] = -l * normal_[v];
    total += reaction_[v];
    if (l > 0) {
      addPointForce(mesh, organ_->vertex(v), reaction_[v], f);
      touching_.push_back(v);
      anchor_.push_back(organ_->vertex(v).interpolate(mesh, x));
    }
  }
  return f;
}

VecX SkullContact::frozenLoad(const HexMesh& mesh, const EmbeddedSurface& organ) const {
  VecX f = VecX::Zero(mesh.numDofs());
  for (int v = 0; v < numVertices(); ++v)
    if (reaction_[v].squaredNorm() > 0) addPointForce(mesh, organ.vertex(v), reaction_[v], f);
  return f;
}

ElementBlocks SkullContact::supportStiffness(const EmbeddedSurface& organ) const {
  ElementBlocks K;
  std::map<int, size_t> slot;
  for (int v : touching_) addVertexBlock(organ.vertex(v), k_[v] * normal_[v] * normal_[v].transpose(), slot, K);
  return K;
}

VecX SkullContact::supportAnchorLoad(const HexMesh& mesh, const EmbeddedSurface& organ) const {
  VecX f = VecX::Zero(mesh.numDofs());
  for (size_t i = 0; i < touching_.size(); ++i) {
    const int v = touching_[i];
    addPointForce(mesh, organ.vertex(v), k_[v] * normal_[v] * normal_[v].dot(anchor_[i]), f);
  }
  return f;
}

}  // namespace needle_sim
