#include "needle_sim/fem/hex8.hpp"

#include <Eigen/Cholesky>
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

namespace {

// The Voigt strain of N vector fields with gradients g (row a: grad of field a), each carrying
// three components: the columns 3a..3a+2.
template <int N>
Eigen::Matrix<double, 6, 3 * N> voigtStrain(const Eigen::Matrix<double, N, 3>& g) {
  Eigen::Matrix<double, 6, 3 * N> B = Eigen::Matrix<double, 6, 3 * N>::Zero();
  for (int a = 0; a < N; ++a) {
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

}  // namespace

Eigen::Matrix<double, 6, 24> strainDisplacement(const Mat83& g) { return voigtStrain<8>(g); }

namespace {

using Strain24 = Eigen::Matrix<double, 6, 24>;
using Strain9 = Eigen::Matrix<double, 6, 9>;

bool usesBbar(HexFormulation f) { return f == HexFormulation::Bbar || f == HexFormulation::IncompatibleModesBbar; }
bool usesModes(HexFormulation f) {
  return f == HexFormulation::IncompatibleModes || f == HexFormulation::IncompatibleModesBbar;
}

// A strain operator whose volume strain m^T S is pulled towards the element mean:
// S + (1 - keep) m (mean - m^T S) / 3, i.e. the volume strain becomes mean + keep (m^T S - mean).
// keep = 0 is B-bar (the mean everywhere).
template <int N>
Eigen::Matrix<double, 6, N> withVolumetric(const Eigen::Matrix<double, 6, N>& S, const Eigen::Matrix<double, 1, N>& mean,
                                           double keep = 0.0) {
  const Eigen::Matrix<double, 1, N> shift = (1.0 - keep) * (mean - S.template topRows<3>().colwise().sum()) / 3.0;
  Eigen::Matrix<double, 6, N> out = S;
  out.template topRows<3>().rowwise() += shift;
  return out;
}

// The strain of the nine incompatible modes u_i = (1 - xi_k^2) alpha_(3k+i) at xi, in Taylor's
// form: gradients through the centroid's dxi/dX, scaled by det J0 / det J(xi).
Strain9 modeStrain(const Eigen::Vector3d& xi, const Eigen::Matrix3d& J0inv, double det0, double detJ) {
  Eigen::Matrix3d natural = Eigen::Matrix3d::Zero();  // row k: d(1 - xi_k^2)/dxi
  for (int k = 0; k < 3; ++k) natural(k, k) = -2.0 * xi[k];
  const Eigen::Matrix3d g = (det0 / detJ) * natural * J0inv;  // row k: dM_k/dX
  return voigtStrain<3>(g);
}

// How much of the volume strain's variation over the element the formulation keeps (see
// hex8.hpp): none for Bbar; for incompatible modes with Bbar, enough that the variation costs
// what it would in a material of the same mu at kVolumeFluctuationPoisson, K s^2 = K(0.3).
// Locking comes from a bulk modulus far above mu; below it the element is the incompatible
// modes' own. A pure mean (s = 0) under the modes is too soft in bending: a one-element-thick
// cantilever bent 3.5 times too far at nu = 0.3 and 2.8 times at 0.4999 (with the modes'
// volume strain kept whole), and with the modes made deviatoric too, three zero-energy modes
// appear (they cancel the deviatoric strain of hourglass combinations whose volume strain the
// mean drops).
double volumeFluctuation(HexFormulation f, const LinearElasticMaterial& m) {
  if (f != HexFormulation::IncompatibleModesBbar) return 0.0;
  const double mu = m.lameMu(), bulk = m.lameLambda() + 2.0 * mu / 3.0;
  const double nu0 = kVolumeFluctuationPoisson;
  const double bulk0 = 2.0 * mu * (1.0 + nu0) / (3.0 * (1.0 - 2.0 * nu0));
  return bulk <= bulk0 ? 1.0 : std::sqrt(bulk0 / bulk);
}

Eigen::Vector3d gaussPoint(int i) {
  const double g = 1.0 / std::sqrt(3.0);
  return Eigen::Vector3d(kCornerSigns[i][0] * g, kCornerSigns[i][1] * g, kCornerSigns[i][2] * g);
}

}  // namespace

ElementReference computeReference(const Mat83& X, const LinearElasticMaterial& material) {
  ElementReference ref;
  ref.formulation = material.element;
  ref.node_volume.setZero();
  ref.mean_dilatation.setZero();
  ref.modes.setZero();
  const Eigen::Matrix<double, 6, 6> D = material.elasticity();
  std::array<Strain24, 8> B;
  std::array<double, 8> detJ{};
  for (int q = 0; q < 8; ++q) {
    const Eigen::Vector3d xi = gaussPoint(q);
    const Mat83 Gn = shapeGradNatural(xi);
    const Eigen::Matrix3d J = X.transpose() * Gn;  // J_ij = dX_i / dxi_j
    detJ[q] = J.determinant();
    if (!(detJ[q] > 0)) throw std::invalid_argument("hex8 element is degenerate or inverted");
    B[q] = strainDisplacement(Gn * J.inverse());  // dN/dX = dN/dxi * dxi/dX
    ref.node_volume += shape(xi) * detJ[q];
    ref.volume += detJ[q];
    ref.mean_dilatation += B[q].topRows<3>().colwise().sum() * detJ[q];
  }
  ref.mean_dilatation /= ref.volume;
  const Mat83 Gc = shapeGradNatural(Eigen::Vector3d::Zero());
  const Eigen::Matrix3d Jc = X.transpose() * Gc;
  ref.centroid_det = Jc.determinant();
  if (!(ref.centroid_det > 0)) throw std::invalid_argument("hex8 element is degenerate");
  ref.centroid_inverse_jacobian = Jc.inverse();
  ref.grad_centroid = Gc * ref.centroid_inverse_jacobian;

  const bool bbar = usesBbar(ref.formulation), modes = usesModes(ref.formulation);
  ref.volume_fluctuation = volumeFluctuation(ref.formulation, material);
  Mat24 Kuu = Mat24::Zero();
  Eigen::Matrix<double, 9, 24> Kau = Eigen::Matrix<double, 9, 24>::Zero();
  Eigen::Matrix<double, 9, 9> Kaa = Eigen::Matrix<double, 9, 9>::Zero();
  for (int q = 0; q < 8; ++q) {
    const Strain24 Bq = bbar ? withVolumetric<24>(B[q], ref.mean_dilatation, ref.volume_fluctuation) : B[q];
    Kuu.noalias() += Bq.transpose() * D * Bq * detJ[q];
    if (!modes) continue;
    Strain9 G = modeStrain(gaussPoint(q), ref.centroid_inverse_jacobian, ref.centroid_det, detJ[q]);
    if (bbar) G = withVolumetric<9>(G, Eigen::Matrix<double, 1, 9>::Zero(), ref.volume_fluctuation);
    Kau.noalias() += G.transpose() * D * Bq * detJ[q];
    Kaa.noalias() += G.transpose() * D * G * detJ[q];
  }
  if (modes) {
    // Static condensation: the modes minimise the energy for given corner displacements.
    const Eigen::LLT<Eigen::Matrix<double, 9, 9>> llt(0.5 * (Kaa + Kaa.transpose()));
    if (llt.info() != Eigen::Success) throw std::invalid_argument("hex8 element's incompatible modes are singular");
    ref.modes = llt.solve(Kau);
    Kuu.noalias() -= Kau.transpose() * ref.modes;
  }
  ref.K0 = 0.5 * (Kuu + Kuu.transpose());
  return ref;
}

Eigen::Matrix<double, 6, 24> strainOperator(const Mat83& X, const ElementReference& ref, const Eigen::Vector3d& xi) {
  const Mat83 Gn = shapeGradNatural(xi);
  const Eigen::Matrix3d J = X.transpose() * Gn;
  Strain24 E = strainDisplacement(Gn * J.inverse());
  const bool bbar = usesBbar(ref.formulation);
  if (bbar) E = withVolumetric<24>(E, ref.mean_dilatation, ref.volume_fluctuation);
  if (usesModes(ref.formulation)) {
    Strain9 G = modeStrain(xi, ref.centroid_inverse_jacobian, ref.centroid_det, J.determinant());
    if (bbar) G = withVolumetric<9>(G, Eigen::Matrix<double, 1, 9>::Zero(), ref.volume_fluctuation);
    E.noalias() -= G * ref.modes;
  }
  return E;
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
