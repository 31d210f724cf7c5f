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
  Mat24 K0;                  // rest stiffness, 2x2x2 Gauss
  Mat83 grad_centroid;       // dN_a/dX at the centroid (deformation gradient, stresses)
  Vec8 node_volume;          // integral of N_a over the element (lumped mass, body force)
  double volume = 0.0;
};

// Computes the reference matrices of the element with rest corner positions X (8x3).
// Throws std::invalid_argument if the element is degenerate or inverted at a Gauss point.
ElementReference computeReference(const Mat83& X, const LinearElasticMaterial& material);

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
