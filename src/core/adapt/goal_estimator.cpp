#include "needle_sim/adapt/goal_estimator.hpp"

#include <cmath>

namespace needle_sim {

Vec3 TargetQoi::value(const HexMesh& mesh, const VecX& x) const {
  Vec3 m = Vec3::Zero();
  for (const auto& s : samples) m += s.interpolate(mesh, x) - s.rest;
  return samples.empty() ? m : Vec3(m / static_cast<double>(samples.size()));
}

Eigen::MatrixXd TargetQoi::load(const HexMesh& mesh) const {
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(mesh.numDofs(), 3);
  const double w = samples.empty() ? 0.0 : 1.0 / samples.size();
  for (const auto& s : samples) {
    const auto& el = mesh.element(s.element);
    for (int a = 0; a < 8; ++a)
      for (int k = 0; k < 3; ++k) G(3 * el[a] + k, k) += w * s.weights[a];
  }
  return G;
}

TargetQoi targetQoi(const HexMesh& mesh, const PointLocator& locator, const Vec3& centre, double radius) {
  TargetQoi q;
  EmbeddedPoint ep;
  if (locator.locate(centre, ep)) q.samples.push_back(ep);
  if (radius <= 0) return q;
  constexpr int kN = 5;
  for (int i = 0; i < kN; ++i)
    for (int j = 0; j < kN; ++j)
      for (int k = 0; k < kN; ++k) {
        const Vec3 d = radius * (2.0 * Vec3(i, j, k) / (kN - 1) - Vec3::Ones());
        if (d.norm() > radius + 1e-12 || d.norm() == 0) continue;
        if (locator.locate(centre + d, ep)) q.samples.push_back(ep);
      }
  return q;
}

TargetError goalEstimate(const SprEstimator& spr, const VecX& x, const VecX* reference, const ErrorEstimate& primal,
                         const Eigen::MatrixXd& Z, const TargetQoi& qoi, const HexMesh& mesh) {
  TargetError t;
  t.eta_u = primal.global;
  t.qoi = qoi.value(mesh, x) - (reference ? qoi.value(mesh, *reference) : Vec3::Zero());
  t.indicator.assign(mesh.numElements(), 0.0);
  std::vector<double> zsq(mesh.numElements(), 0.0);
  for (int k = 0; k < 3; ++k) {
    const SprEstimator::DualIndicators d = spr.dual(x, reference, primal, Z.col(k));
    t.estimate[k] = d.mixed_total;
    t.eta_z[k] = d.global;
    t.global_component_bound[k] = primal.global * d.global;
    for (int e = 0; e < mesh.numElements(); ++e) {
      zsq[e] += d.eta[e] * d.eta[e];
      t.component_bound[k] += std::abs(d.mixed[e]);
    }
  }
  for (int e = 0; e < mesh.numElements(); ++e) t.indicator[e] = primal.eta[e] * std::sqrt(zsq[e]);
  t.bound = t.component_bound.norm();
  t.global_bound = t.global_component_bound.norm();
  t.valid = true;
  return t;
}

}  // namespace needle_sim
