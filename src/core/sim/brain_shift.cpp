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
// Relative residual of a rough solve (a pass of the adaptive pre-step that only feeds the
// error estimate).
constexpr double kRoughTolerance = 1e-3;

// Size of the (coarse) grid's first cell: the length scale of the penalty and tolerances.
double cellSize(const HexMesh& mesh) {
  const Eigen::Matrix<double, 8, 3> X = mesh.elementCorners(0);
  return (X.colwise().maxCoeff() - X.colwise().minCoeff()).maxCoeff();
}

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
    // Only the part above the CSF level has lost its buoyancy: the fraction of the cell
    // above the plane (sampled in cells it cuts, so that coarse and refined meshes carry the
    // same load).
    double above = 1;
    if (!scene_.all) {
      const Eigen::Matrix<double, 8, 3> X = mesh.elementCorners(e);
      int n_above = 0;
      for (int a = 0; a < 8; ++a) n_above += up.dot(X.row(a).transpose() - scene_.csf_point) > 0;
      if (n_above == 0) continue;  // still buoyant in CSF
      if (n_above < 8) {
        constexpr int kS = 16;
        int hits = 0;
        for (int i = 0; i < kS; ++i)
          for (int j = 0; j < kS; ++j)
            for (int k = 0; k < kS; ++k) {
              const Vec3 xi((i + 0.5) / kS, (j + 0.5) / kS, (k + 0.5) / kS);
              const Vec3 p = X.transpose() * hex8::shape(2 * xi - Vec3::Ones());
              hits += up.dot(p - scene_.csf_point) > 0;
            }
        above = static_cast<double>(hits) / (kS * kS * kS);
      }
    }
    const auto& nv = model.reference(e).node_volume;  // weighted by the volume fraction
    for (int a = 0; a < 8; ++a) node3(f, mesh.element(e)[a]) += above * nv[a] * b;
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
    addVertexBlock(ep, k_[v] * normal_[v] * normal_[v].transpose(), slot, K);
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

BrainShiftResult BrainShift::apply(TissueBody& body, const EmbeddedPoint* target, double start_scale, bool rough,
                                   bool calibrate) {
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
  // 0.1 % of the gap (1 % on a rough pass)
  const double pen_tol = (rough ? 1e-2 : 1e-3) * std::max(scene_.gap, 1e-3 * cellSize(body.mesh()));
  TissueBody::ExtraForce extra;
  if (with_contact) extra = [this, &body](const VecX& x, VecX& f, ElementBlocks& K) { contact(body, x, f, K); };

  double applied = 0;  // scale of the load now in the body
  const double tol = rough ? std::max(scene_.tolerance, kRoughTolerance) : scene_.tolerance;
  // Newton solves with multiplier updates until the penetration is within tolerance.
  // loose: to the rough tolerances (the steps towards target_shift's scale).
  auto solveContact = [&](bool loose, TissueBody::LoadControl* control) {
    loose = loose || rough;
    for (int pass = 0; pass < (loose ? 2 : 20); ++pass) {
      const StepStats st = body.solveStatic(extra, loose ? std::max(tol, kRoughTolerance) : tol, 50, control);
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
  };
  auto setScale = [&](double scale) {
    body.addExternalForce((scale - applied) * unit);
    applied = scale;
  };
  auto targetMotion = [&]() { return target ? Vec3(target->interpolate(body.mesh(), body.positions()) - target->rest) : Vec3::Zero(); };

  try {
    const bool at_rest = (body.positions() - body.mesh().restPositions()).squaredNorm() == 0;
    const bool control = calibrate && scene_.target_shift && target;
    // From rest, the load in steps (the controlled solve needs the target to have moved to
    // know its direction); from an earlier shift (a refined mesh), the controlled solve at once.
    const int steps = at_rest ? scene_.load_steps : control ? 0 : 1;
    if (steps == 0) setScale(start_scale);
    for (int k = 1; k <= steps; ++k) {
      setScale(start_scale * k / steps);
      solveContact(control, nullptr);  // rough when the scale is solved for next
    }
    res.load_scale = applied;
    if (control) {
      // target_shift: displacement control, |d(x)| = want with the load scale unknown (the
      // bordered Newton of TissueBody::solveStatic), to 1 % on a rough pass, 0.1 % else.
      const double want = *scene_.target_shift;
      const double accuracy = rough ? 1e-2 : 1e-3;
      const HexMesh& mesh = body.mesh();
      const auto& el = mesh.element(target->element);
      TissueBody::LoadControl lc;
      lc.unit = &unit;
      lc.scale = applied;
      lc.tolerance = 0.25 * accuracy * want;
      lc.constraint = [&](const VecX& x, VecX& g) {
        const Vec3 d = target->interpolate(mesh, x) - target->rest;
        const double n = d.norm();
        if (!(n > 0)) throw NumericalError(-1, "brain shift: the target does not move with the load");
        for (int a = 0; a < 8; ++a) node3(g, el[a]) += target->weights[a] * d / n;
        return n - want;
      };
      try {
        solveContact(rough, &lc);
      } catch (const NumericalError& e) {
        throw NumericalError(-1, "brain shift: could not reach target_shift " + std::to_string(want) + " m (" +
                                     e.what() + ")");
      }
      applied = lc.scale;
      const double got = targetMotion().norm();
      if (std::abs(got - want) > accuracy * want)
        throw NumericalError(-1, "brain shift: could not reach target_shift " + std::to_string(want) + " m (got " +
                                     std::to_string(got) + " m)");
      res.load_scale = applied;
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
    touching_.clear();
    anchor_.clear();
    for (size_t v = 0; v < lambda_.size(); ++v) {
      const EmbeddedPoint& ep = organ_->vertex(static_cast<int>(v));
      const Vec3 p = ep.interpolate(body.mesh(), body.positions());
      const double g = normal_[v].dot(p - rest_[v]) - offset_[v];
      const double l = std::max(0.0, lambda_[v] + k_[v] * g);
      skull_force_[v] = -l * normal_[v];
      total += skull_force_[v];
      if (l > 0) {
        touching_.push_back(static_cast<int>(v));
        anchor_.push_back(p);
      }
    }
    res.skull_force = total.norm();
    res.max_penetration = penetration(body, res.contacts);
  }
  if (target) res.target_displacement = target->interpolate(body.mesh(), body.positions()) - target->rest;
  res.max_displacement = 0;
  const VecX u = body.displacements();
  for (int i = 0; i < body.mesh().numNodes(); ++i) res.max_displacement = std::max(res.max_displacement, node3(u, i).norm());
  res.done = true;
  res.passes = 1;
  res.dofs = body.mesh().numDofs();
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

namespace needle_sim {

ElementBlocks BrainShift::supportStiffness(const EmbeddedSurface& organ) const {
  ElementBlocks K;
  if (!hasSupport()) return K;
  std::map<int, size_t> slot;
  for (int v : touching_) addVertexBlock(organ.vertex(v), k_[v] * normal_[v] * normal_[v].transpose(), slot, K);
  return K;
}

VecX BrainShift::supportAnchorLoad(const TissueBody& body, const EmbeddedSurface& organ) const {
  VecX f = VecX::Zero(body.mesh().numDofs());
  if (!hasSupport()) return f;
  for (size_t i = 0; i < touching_.size(); ++i) {
    const int v = touching_[i];
    const EmbeddedPoint& ep = organ.vertex(v);
    const Vec3 fa = k_[v] * normal_[v] * normal_[v].dot(anchor_[i]);
    const auto& el = body.mesh().element(ep.element);
    for (int a = 0; a < 8; ++a) node3(f, el[a]) += ep.weights[a] * fa;
  }
  return f;
}

}  // namespace needle_sim
