#include "needle_sim/sim/brain_shift.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

namespace {
// Penalty per unit area, in units of (tissue E / cell size). Larger needs fewer multiplier
// updates but more Newton iterations as contacts switch; 3e3 was fastest on the DBS scene.
constexpr double kPenalty = 3e3;

// Size of the (coarse) grid's first cell: the length scale of the penalty and tolerances.
double cellSize(const HexMesh& mesh) {
  const Eigen::Matrix<double, 8, 3> X = mesh.elementCorners(0);
  return (X.colwise().maxCoeff() - X.colwise().minCoeff()).maxCoeff();
}
}  // namespace

BrainShift::BrainShift(const BrainShiftScene& scene, const TissueScene& tissue, const EmbeddedSurface* organ)
    : scene_(scene), density_(scene.density.value_or(tissue.material.density)), organ_(organ) {
  if (!organ_ || !scene_.skull_contact) return;
  const TriangleMesh& m = organ_->rest();
  std::vector<double> area;
  m.vertexNormals(normal_, area);
  offset_.assign(m.numVertices(), scene_.gap);
  if (scene_.skull) {
    // The skull's tangent plane nearest each vertex: normal from the vertex to the skull.
    const TriangleMesh& sk = *scene_.skull;
    for (int v = 0; v < m.numVertices(); ++v) {
      const Vec3& X = m.vertex(v);
      double best = 1e300;
      Vec3 q = X;
      for (int t = 0; t < sk.numTriangles(); ++t) {
        const auto& tr = sk.triangle(t);
        const Vec3 c = closestPointOnTriangle(X, sk.vertex(tr[0]), sk.vertex(tr[1]), sk.vertex(tr[2]));
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
  const double E = tissue.material.young;
  const double cell = cellSize(organ_->mesh());
  k_.resize(m.numVertices());
  for (int v = 0; v < m.numVertices(); ++v) k_[v] = kPenalty * E / cell * area[v];
  lambda_.assign(m.numVertices(), 0.0);
  skull_force_.assign(m.numVertices(), Vec3::Zero());
}

VecX BrainShift::unitLoad(const TissueBody& body) const {
  const HexMesh& mesh = body.mesh();
  const CorotationalHexModel& model = body.model();
  VecX f = VecX::Zero(mesh.numDofs());
  const Vec3 up = -scene_.gravity.normalized();
  const Vec3 b = density_ * scene_.gravity;  // N/m^3
  for (int e = 0; e < mesh.numElements(); ++e) {
    const Vec3 c = mesh.elementCorners(e).colwise().mean().transpose();
    if (!scene_.all && up.dot(c - scene_.csf_point) <= 0) continue;  // still buoyant in CSF
    const auto& nv = model.reference(e).node_volume;                   // weighted by the fraction
    for (int a = 0; a < 8; ++a) node3(f, mesh.element(e)[a]) += nv[a] * b;
  }
  return f;
}

void BrainShift::contact(const TissueBody& body, const VecX& x, VecX& f, ElementBlocks& K) const {
  const HexMesh& mesh = body.mesh();
  std::map<int, size_t> slot;
  for (size_t v = 0; v < lambda_.size(); ++v) {
    const EmbeddedPoint& ep = organ_->vertex(static_cast<int>(v));
    const Vec3 p = ep.interpolate(mesh, x);
    const double g = normal_[v].dot(p - rest_[v]) - offset_[v];
    const double l = lambda_[v] + k_[v] * g;
    if (l <= 0) continue;
    const auto& el = mesh.element(ep.element);
    for (int a = 0; a < 8; ++a) node3(f, el[a]) -= ep.weights[a] * l * normal_[v];
    auto it = slot.find(ep.element);
    if (it == slot.end()) {
      it = slot.emplace(ep.element, K.element.size()).first;
      K.element.push_back(ep.element);
      K.K.push_back(hex8::Mat24::Zero());
    }
    const Mat3 nn = k_[v] * normal_[v] * normal_[v].transpose();
    hex8::Mat24& B = K.K[it->second];
    for (int a = 0; a < 8; ++a)
      for (int c = 0; c < 8; ++c) B.block<3, 3>(3 * a, 3 * c) += ep.weights[a] * ep.weights[c] * nn;
  }
}

double BrainShift::penetration(const TissueBody& body, int& active) const {
  double worst = 0;
  active = 0;
  for (size_t v = 0; v < lambda_.size(); ++v) {
    const EmbeddedPoint& ep = organ_->vertex(static_cast<int>(v));
    const double g = normal_[v].dot(ep.interpolate(body.mesh(), body.positions()) - rest_[v]) - offset_[v];
    worst = std::max(worst, g);
    active += lambda_[v] + k_[v] * g > 0;
  }
  return worst;
}

BrainShiftResult BrainShift::apply(TissueBody& body, const EmbeddedPoint* target) {
  const auto t0 = std::chrono::steady_clock::now();
  BrainShiftResult res;
  const VecX unit = unitLoad(body);
  // Gaps from the vertices' interpolated rest positions, so that g is exactly -c at rest.
  if (!lambda_.empty()) {
    const VecX X = body.mesh().restPositions();
    rest_.resize(lambda_.size());
    for (size_t v = 0; v < lambda_.size(); ++v) rest_[v] = organ_->vertex(static_cast<int>(v)).interpolate(body.mesh(), X);
  }
  const bool with_contact = !lambda_.empty();
  const double pen_tol = 1e-3 * std::max(scene_.gap, 1e-3 * cellSize(body.mesh()));  // 0.1 % of the gap
  TissueBody::ExtraForce extra;
  if (with_contact) extra = [this, &body](const VecX& x, VecX& f, ElementBlocks& K) { contact(body, x, f, K); };

  double applied = 0;  // scale of the load now in the body
  // Solve for the load at `scale`, in load steps from the current one, with multiplier
  // updates until the penetration is within tolerance.
  auto solveAt = [&](double scale) {
    const int steps = res.load_solves == 0 ? scene_.load_steps : 1;
    const double from = applied;
    for (int s = 1; s <= steps; ++s) {
      const double to = from + (scale - from) * s / steps;
      body.addExternalForce((to - applied) * unit);
      applied = to;
      for (int pass = 0; pass < 20; ++pass) {
        const StepStats st = body.solveStatic(extra, scene_.tolerance, 50);
        res.newton_iterations += st.newton_iterations;
        res.factorizations += st.factorizations;
        res.factor_ms += st.factor_ms + st.assemble_ms;
        res.solve_ms += st.solve_ms + st.forces_ms;
        if (!with_contact) break;
        int active = 0;
        const double pen = penetration(body, active);
        if (pen <= pen_tol) break;
        ++res.multiplier_updates;
        for (size_t v = 0; v < lambda_.size(); ++v) {
          const EmbeddedPoint& ep = organ_->vertex(static_cast<int>(v));
          const double g = normal_[v].dot(ep.interpolate(body.mesh(), body.positions()) - rest_[v]) - offset_[v];
          lambda_[v] = std::max(0.0, lambda_[v] + k_[v] * g);
        }
      }
      ++res.load_solves;
    }
  };
  auto targetShift = [&]() {
    return target ? (target->interpolate(body.mesh(), body.positions()) - target->rest).norm() : 0.0;
  };

  try {
    solveAt(1.0);
    res.load_scale = 1.0;
    if (scene_.target_shift && target) {
      // Secant iterations on d(scale) = target_shift, starting from d(0) = 0.
      const double want = *scene_.target_shift;
      double s0 = 0, d0 = 0, s1 = 1, d1 = targetShift();
      for (int it = 0; it < 12 && std::abs(d1 - want) > 1e-3 * want; ++it) {
        const double slope = (d1 - d0) / (s1 - s0);
        if (!(slope > 0)) throw NumericalError(-1, "brain shift: the target does not move with the load");
        double s2 = s1 + (want - d1) / slope;
        s2 = std::clamp(s2, 0.25 * s1, 4 * s1);
        if (s2 > 1e3)
          throw NumericalError(-1, "brain shift: target_shift " + std::to_string(want) +
                                       " m is out of reach (the skull and clamps hold the target)");
        solveAt(s2);
        s0 = s1;
        d0 = d1;
        s1 = s2;
        d1 = targetShift();
      }
      if (std::abs(d1 - want) > 1e-2 * want)
        throw NumericalError(-1, "brain shift: could not reach target_shift " + std::to_string(want) + " m (got " +
                                     std::to_string(d1) + " m)");
      res.load_scale = s1;
    }
  } catch (const NumericalError& e) {
    throw NumericalError(0, std::string(e.what()) + " (brain-shift pre-step)");
  }

  // Freeze the skull reactions as loads: the shifted state is then an equilibrium without
  // the contact terms.
  if (with_contact) {
    VecX f = VecX::Zero(body.mesh().numDofs());
    ElementBlocks K;
    contact(body, body.positions(), f, K);
    body.addExternalForce(f);
    Vec3 total = Vec3::Zero();
    for (size_t v = 0; v < lambda_.size(); ++v) {
      const EmbeddedPoint& ep = organ_->vertex(static_cast<int>(v));
      const double g = normal_[v].dot(ep.interpolate(body.mesh(), body.positions()) - rest_[v]) - offset_[v];
      const double l = std::max(0.0, lambda_[v] + k_[v] * g);
      skull_force_[v] = -l * normal_[v];
      total += skull_force_[v];
    }
    res.skull_force = total.norm();
    res.max_penetration = penetration(body, res.contacts);
  }
  if (target) res.target_displacement = target->interpolate(body.mesh(), body.positions()) - target->rest;
  res.max_displacement = 0;
  const VecX u = body.displacements();
  for (int i = 0; i < body.mesh().numNodes(); ++i) res.max_displacement = std::max(res.max_displacement, node3(u, i).norm());
  res.done = true;
  res.ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

VecX BrainShift::skullLoad(const TissueBody& body, const EmbeddedSurface& organ) const {
  VecX f = VecX::Zero(body.mesh().numDofs());
  for (size_t v = 0; v < skull_force_.size(); ++v) {
    if (skull_force_[v].squaredNorm() == 0) continue;
    const EmbeddedPoint& ep = organ.vertex(static_cast<int>(v));
    const auto& el = body.mesh().element(ep.element);
    for (int a = 0; a < 8; ++a) node3(f, el[a]) += ep.weights[a] * skull_force_[v];
  }
  return f;
}

}  // namespace needle_sim
