#include "needle_sim/fem/hex8.hpp"

#include <Eigen/LU>
#include <cmath>
#include <stdexcept>

namespace needle_sim {
namespace hex8 {

const std::array<std::array<int, 3>, 8> kCornerSigns = {{{-1, -1, -1},
                                                         {+1, -1, -1},
                                                         {+1, +1, -1},
                                                         {-1, +1, -1},
                                                         {-1, -1, +1},
                                                         {+1, -1, +1},
                                                         {+1, +1, +1},
                                                         {-1, +1, +1}}};

const std::array<std::array<int, 4>, 6> kFaces = {{{0, 3, 2, 1},    // zeta = -1
                                                   {4, 5, 6, 7},    // zeta = +1
                                                   {0, 1, 5, 4},    // eta = -1
                                                   {2, 3, 7, 6},    // eta = +1
                                                   {0, 4, 7, 3},    // xi = -1
                                                   {1, 2, 6, 5}}};  // xi = +1

Vec8 shape(const Eigen::Vector3d& xi) {
  Vec8 N;
  for (int a = 0; a < 8; ++a) {
    const auto& s = kCornerSigns[a];
    N[a] = 0.125 * (1 + s[0] * xi[0]) * (1 + s[1] * xi[1]) * (1 + s[2] * xi[2]);
  }
  return N;
}

Mat83 shapeGradNatural(const Eigen::Vector3d& xi) {
  Mat83 G;
  for (int a = 0; a < 8; ++a) {
    const auto& s = kCornerSigns[a];
    const double f0 = 1 + s[0] * xi[0], f1 = 1 + s[1] * xi[1], f2 = 1 + s[2] * xi[2];
    G(a, 0) = 0.125 * s[0] * f1 * f2;
    G(a, 1) = 0.125 * f0 * s[1] * f2;
    G(a, 2) = 0.125 * f0 * f1 * s[2];
  }
  return G;
}

Eigen::Matrix<double, 6, 24> strainDisplacement(const Mat83& g) {
  Eigen::Matrix<double, 6, 24> B = Eigen::Matrix<double, 6, 24>::Zero();
  for (int a = 0; a < 8; ++a) {
    const int c = 3 * a;
    B(0, c + 0) = g(a, 0);
    B(1, c + 1) = g(a, 1);
    B(2, c + 2) = g(a, 2);
    B(3, c + 0) = g(a, 1);
    B(3, c + 1) = g(a, 0);
    B(4, c + 1) = g(a, 2);
    B(4, c + 2) = g(a, 1);
    B(5, c + 0) = g(a, 2);
    B(5, c + 2) = g(a, 0);
  }
  return B;
}

ElementReference computeReference(const Mat83& X, const LinearElasticMaterial& material) {
  ElementReference ref;
  ref.K0.setZero();
  ref.node_volume.setZero();
  const Eigen::Matrix<double, 6, 6> D = material.elasticity();
  const double g = 1.0 / std::sqrt(3.0);
  for (int i = 0; i < 8; ++i) {
    const Eigen::Vector3d xi(kCornerSigns[i][0] * g, kCornerSigns[i][1] * g,
                             kCornerSigns[i][2] * g);
    const Mat83 Gn = shapeGradNatural(xi);
    const Eigen::Matrix3d J = X.transpose() * Gn;  // J_ij = dX_i / dxi_j
    const double detJ = J.determinant();
    if (!(detJ > 0)) throw std::invalid_argument("hex8 element is degenerate or inverted");
    const Mat83 grad = Gn * J.inverse();  // dN/dX = dN/dxi * dxi/dX
    const Eigen::Matrix<double, 6, 24> B = strainDisplacement(grad);
    ref.K0.noalias() += B.transpose() * D * B * detJ;
    ref.node_volume += shape(xi) * detJ;
    ref.volume += detJ;
  }
  ref.K0 = 0.5 * (ref.K0 + ref.K0.transpose()).eval();
  const Mat83 Gc = shapeGradNatural(Eigen::Vector3d::Zero());
  const Eigen::Matrix3d Jc = X.transpose() * Gc;
  if (!(Jc.determinant() > 0)) throw std::invalid_argument("hex8 element is degenerate");
  ref.grad_centroid = Gc * Jc.inverse();
  return ref;
}

ShapeKey shapeKey(const Mat83& X, double quantum) {
  ShapeKey k{};
  int c = 0;
  for (int a = 1; a < 8; ++a)
    for (int d = 0; d < 3; ++d) k[c++] = std::llround((X(a, d) - X(0, d)) / quantum);
  return k;
}

bool inverseMap(const Mat83& X, const Eigen::Vector3d& p, Eigen::Vector3d& xi) {
  xi.setZero();
  const double scale = (X.colwise().maxCoeff() - X.colwise().minCoeff()).norm();
  for (int it = 0; it < 30; ++it) {
    const Eigen::Vector3d r = X.transpose() * shape(xi) - p;
    if (r.norm() <= 1e-13 * scale) return true;
    const Eigen::Matrix3d J = X.transpose() * shapeGradNatural(xi);
    Eigen::Vector3d step = J.partialPivLu().solve(r);
    if (!step.allFinite()) return false;
    xi -= step;
    if (xi.cwiseAbs().maxCoeff() > 10) return false;  // far outside: not this element
  }
  return (X.transpose() * shape(xi) - p).norm() <= 1e-10 * scale;
}

}  // namespace hex8
}  // namespace needle_sim
