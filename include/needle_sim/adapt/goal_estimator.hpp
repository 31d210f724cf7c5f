#pragma once
// Goal-oriented estimate of the error on a target's displacement (doc/method.md, "Error on
// target motion"). The quantity of interest is the target's displacement, component by
// component, regularised as its mean over a small ball of material points around the
// target (radius about one finest element; the displacement at a point is not bounded in
// 3D elasticity): Q_k(u) = mean_s u_k(X_s). Its dual problems, K z_k = g_k with g_k the
// load of Q_k, are solved with a factor of K (solver/stiffness_factor.hpp; one 3-column solve).
// Galerkin orthogonality gives Q_k(u) - Q_k(u_h) = a(u - u_h, z_k - z_k,h); both errors are
// taken from SPR recovery (the recovery-based goal estimate of Gonzalez-Estrada, Rodenas,
// Nadal, Bordas and Kerfriden), per element
//     E_k,e = int_e (sigma*_u - sigma_u)^T D^-1 (sigma*_zk - sigma_zk) dV,
// a signed estimate E_k = sum_e E_k,e, and the bound (the sum of the absolute element
// contributions, as in the dual-weighted residual method of Becker and Rannacher)
//     |Q_k(u) - Q_k(u_h)| = |sum_e a_e(u - u_h, z_k - z_k,h)| <= sum_e |a_e(...)| ~ sum_e |E_k,e|,
// on the norm: its Euclidean norm over k. Cauchy-Schwarz on each element, sum_e eta_u,e
// eta_zk,e, and on the whole mesh, eta_u eta_zk (the bound before 2026-12-05, kept as
// global_bound for comparison), are larger again by as much as the primal and dual errors
// live in different places or directions: measured in doc/verification.md ("Error on target
// motion"). Element indicators for goal-oriented refinement: eta_u,e sqrt(sum_k eta_zk,e^2),
// an upper estimate of each element's sum_k |E_k,e| that does not vanish by cancellation.
// Assumptions: the quasi-static dual at the current configuration (corotational tangent
// without geometric stiffness; inertia left out: the insertions are slow), the needle's
// constraint forces taken as given loads (the dual does not see the constraints).
#include <vector>

#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/fem/hex_mesh.hpp"

namespace needle_sim {

// The regularised point: material points in a ball, equal weights.
struct TargetQoi {
  std::vector<EmbeddedPoint> samples;
  // The mean displacement of the samples for positions x (3n).
  Vec3 value(const HexMesh& mesh, const VecX& x) const;
  // The loads g_k (3n x 3): sum_s N_a(X_s) e_k / n_s.
  Eigen::MatrixXd load(const HexMesh& mesh) const;
};
// Samples on a 5 x 5 x 5 lattice in the ball's cube kept inside the ball and the mesh (the
// centre always); radius 0: the point itself.
TargetQoi targetQoi(const HexMesh& mesh, const PointLocator& locator, const Vec3& centre, double radius);

struct TargetError {
  bool valid = false;           // false: not computed, or the dual solve failed
  Vec3 estimate = Vec3::Zero();  // signed estimate of Q(u) - Q(u_h) [m]
  Vec3 component_bound = Vec3::Zero();  // sum_e |E_k,e| [m]
  double bound = 0;             // bound on |Q(u) - Q(u_h)| [m]: the norm of component_bound
  Vec3 global_component_bound = Vec3::Zero();  // eta_u eta_zk: Cauchy-Schwarz on the whole mesh [m]
  double global_bound = 0;      // its norm [m]
  Vec3 qoi = Vec3::Zero();      // Q(u_h): the regularised displacement [m]
  double eta_u = 0;             // the primal energy-norm estimate
  Vec3 eta_z = Vec3::Zero();    // the duals'
  std::vector<double> indicator;  // per element, for goal-oriented marking
};

// From the primal estimate (SprEstimator::estimate of x, reference) and the dual solutions
// Z (3n x 3) of the three components of a goal functional (the target's loads, or a
// combination of targets' duals: TargetErrorEstimator::underPrescribedShift).
TargetError goalEstimate(const SprEstimator& spr, const VecX& x, const VecX* reference, const ErrorEstimate& primal,
                         const Eigen::MatrixXd& Z, const TargetQoi& qoi, const HexMesh& mesh);

}  // namespace needle_sim
