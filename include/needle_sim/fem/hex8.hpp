#pragma once
// The 8-node trilinear hexahedron: shape functions, quadrature and the element
// matrices computed once at rest.
//
// Node order (VTK_HEXAHEDRON) in natural coordinates xi in [-1,1]^3:
//   0 (-,-,-) 1 (+,-,-) 2 (+,+,-) 3 (-,+,-) 4 (-,-,+) 5 (+,-,+) 6 (+,+,+) 7 (-,+,+)
#include <Eigen/Core>
#include <array>

#include "needle_sim/fem/material.hpp"

namespace needle_sim {
namespace hex8 {

using Mat83 = Eigen::Matrix<double, 8, 3>;  // one row per node
using Mat24 = Eigen::Matrix<double, 24, 24>;
using Vec8 = Eigen::Matrix<double, 8, 1>;

extern const std::array<std::array<int, 3>, 8> kCornerSigns;  // +-1 per node and axis
// The 6 faces, each with 4 nodes ordered counter-clockwise seen from outside.
extern const std::array<std::array<int, 4>, 6> kFaces;

Vec8 shape(const Eigen::Vector3d& xi);
Mat83 shapeGradNatural(const Eigen::Vector3d& xi);  // dN_a / dxi_j

// Everything about one element that depends only on its rest shape and material.
struct ElementReference {
  Mat24 K0;                  // rest stiffness, 2x2x2 Gauss: sum_q E_q^T D E_q det J_q
  Mat83 grad_centroid;       // dN_a/dX at the centroid (deformation gradient, rotation)
  Vec8 node_volume;          // integral of N_a over the element (lumped mass, body force)
  double volume = 0.0;
  // What the element's strain operator E(xi) (strainOperator) needs beyond B(xi):
  HexFormulation formulation = HexFormulation::Trilinear;
  Eigen::Matrix<double, 1, 24> mean_dilatation;  // (1/V) int m^T B dV (Bbar; m = (1,1,1,0,0,0))
  Eigen::Matrix<double, 9, 24> modes;            // condensed mode amplitudes: alpha = -modes u
  Eigen::Matrix3d centroid_inverse_jacobian;     // dxi/dX at the centroid (the modes' gradients)
  double centroid_det = 0.0;                     // det J there
  double volume_fluctuation = 0.0;  // Bbar: the share s of the volume strain's variation kept
};

// IncompatibleModesBbar keeps the volume strain's variation over the element at the stiffness
// it has at this nu (same mu), the rest of the bulk modulus acting on the element's mean.
constexpr double kVolumeFluctuationPoisson = 0.3;

// Computes the reference matrices of the element with rest corner positions X (8x3), with
// material.element's formulation. Throws std::invalid_argument if the element is degenerate
// or inverted at a Gauss point.
ElementReference computeReference(const Mat83& X, const LinearElasticMaterial& material);

// The strain the element computes at natural coordinates xi from its corner displacements u
// (Voigt, engineering shears): eps = E(xi) u. Trilinear: B(xi). Bbar: B with its volumetric
// part replaced by the element mean. Incompatible modes: B - G(xi) modes, G the modes' strain
// in Taylor's form (gradients with the centroid Jacobian, scaled by det J0 / det J(xi), so
// that int G dV = 0 and the element passes the patch test when distorted). Both: P(B(xi) -
// G(xi) modes), P pulling the volume strain towards the element mean, keeping the share
// s = min(1, sqrt(K(kVolumeFluctuationPoisson) / K)) of its variation (K the bulk modulus):
// energy 2 mu |dev eps|^2 + K mean^2 + K s^2 (variation)^2. Stresses, the error estimates and
// K0 all use it.
Eigen::Matrix<double, 6, 24> strainOperator(const Mat83& X, const ElementReference& ref, const Eigen::Vector3d& xi);

// An element's rest shape up to translation, quantised (corner offsets from corner 0 in
// units of `quantum`): elements with equal keys share what depends on the shape alone (a
// grid has a few cell shapes among thousands of cells).
using ShapeKey = std::array<long long, 21>;
ShapeKey shapeKey(const Mat83& X, double quantum);

// Strain-displacement matrix B (6x24) for the given spatial shape-function gradients.
Eigen::Matrix<double, 6, 24> strainDisplacement(const Mat83& grad);

// Natural coordinates of the spatial point p inside the element with corners X (Newton on
// the trilinear map). Returns false if Newton fails; the caller checks the range.
bool inverseMap(const Mat83& X, const Eigen::Vector3d& p, Eigen::Vector3d& xi);

}  // namespace hex8
}  // namespace needle_sim
