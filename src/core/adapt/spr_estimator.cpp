#include "needle_sim/adapt/spr_estimator.hpp"

#include <Eigen/Dense>
#include <array>
#include <cassert>
#include <cmath>

#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

namespace {
// Rotates a Voigt stress: R S R^T.
Stress rotate(const Mat3& R, const Stress& s) {
  Mat3 S;
  S << s[0], s[3], s[5], s[3], s[1], s[4], s[5], s[4], s[2];
  const Mat3 G = R * S * R.transpose();
  Stress o;
  o << G(0, 0), G(1, 1), G(2, 2), G(0, 1), G(1, 2), G(0, 2);
  return o;
}

// Least-squares linear fit sigma(x) = a + b (x - x0) through samples; returns the
// coefficients (4 x 6) and whether the fit is a full 3D one. A full patch (the common
// case) is solved by Householder QR of the m x 4 sample matrix in scaled coordinates (the
// normal equations would square its condition number: on the thin patches at hanging
// nodes the exact patch test lost two digits, more with clang); a rank-deficient one through a
// complete orthogonal decomposition (minimum-norm fit).
// The full fit as a linear map (4 x m) from the samples' values to the coefficients, by one
// Householder QR; false when the patch is too flat or small for a 3D fit.
bool fitMap(const std::vector<Vec3>& pts, const Vec3& x0, Eigen::Matrix<double, 4, Eigen::Dynamic>& F) {
  const int m = static_cast<int>(pts.size());
  if (m < 4) return false;
  double scale = 0;
  for (int i = 0; i < m; ++i) scale = std::max(scale, (pts[i] - x0).norm());
  if (scale == 0) scale = 1;
  Eigen::Matrix<double, Eigen::Dynamic, 4> P(m, 4);
  for (int i = 0; i < m; ++i) {
    P(i, 0) = 1;
    P.block<1, 3>(i, 1) = ((pts[i] - x0) / scale).transpose();
  }
  const Eigen::HouseholderQR<Eigen::Matrix<double, Eigen::Dynamic, 4>> qr(P);
  const Eigen::Vector4d r = qr.matrixQR().topRows<4>().diagonal().cwiseAbs();
  // |R_ii| bounds the singular values from above and below within the sample count:
  // a ratio of 1e-6 is the normal equations' former 1e-12 on eigenvalues.
  if (!(r.minCoeff() > 1e-6 * r.maxCoeff())) return false;
  F = qr.solve(Eigen::MatrixXd::Identity(m, m));
  F.bottomRows<3>() /= scale;
  return true;
}

bool fitLinear(const std::vector<Vec3>& pts, const std::vector<Stress>& vals, const Vec3& x0,
               Eigen::Matrix<double, 4, 6>& coef) {
  const int m = static_cast<int>(pts.size());
  Eigen::Matrix<double, 4, Eigen::Dynamic> F;
  Eigen::Matrix<double, Eigen::Dynamic, 6> V(m, 6);
  for (int i = 0; i < m; ++i) V.row(i) = vals[i].transpose();
  if (fitMap(pts, x0, F)) {
    coef = F * V;
    return true;
  }
  double scale = 0;
  for (int i = 0; i < m; ++i) scale = std::max(scale, (pts[i] - x0).norm());
  if (scale == 0) scale = 1;
  Eigen::MatrixXd P(m, 4);
  for (int i = 0; i < m; ++i) {
    P(i, 0) = 1;
    P.block<1, 3>(i, 1) = ((pts[i] - x0) / scale).transpose();
  }
  Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> cod(P);
  cod.setThreshold(1e-8);
  coef = cod.solve(V);
  coef.bottomRows<3>() /= scale;
  return false;
}

// Shape-function gradients (natural) at the 2x2x2 Gauss points and the centroid.
struct GaussTable {
  std::array<Eigen::Matrix<double, 8, 3>, 8> grad;
  std::array<hex8::Vec8, 8> shape;
  std::array<Vec3, 8> point;
  GaussTable() {
    const double g = 1.0 / std::sqrt(3.0);
    for (int q = 0; q < 8; ++q) {
      const Vec3 xi(hex8::kCornerSigns[q][0] * g, hex8::kCornerSigns[q][1] * g, hex8::kCornerSigns[q][2] * g);
      grad[q] = hex8::shapeGradNatural(xi);
      shape[q] = hex8::shape(xi);
      point[q] = xi;
    }
  }
};
const GaussTable& gaussTable() {
  static const GaussTable t;
  return t;
}
}  // namespace

SprEstimator::SprEstimator(const CorotationalHexModel& model) : model_(model) {
  const HexMesh& mesh = model.mesh();
  node_elements_.resize(mesh.numNodes());
  centroids_.resize(mesh.numElements());
  for (int e = 0; e < mesh.numElements(); ++e) {
    centroids_[e] = mesh.elementCorners(e).colwise().mean().transpose();
    for (int a : mesh.element(e)) node_elements_[a].push_back(e);
  }
  interior_.assign(mesh.numNodes(), 0);
  fit_.resize(mesh.numNodes());
  for (int n = 0; n < mesh.numNodes(); ++n) {
    const int m = static_cast<int>(node_elements_[n].size());
    if (m < 4) continue;
    std::vector<Vec3> pts;
    for (int e : node_elements_[n]) pts.push_back(centroids_[e]);
    interior_[n] = fitMap(pts, mesh.node(n), fit_[n]);
  }
  const GaussTable& gt = gaussTable();
  shapes_.resize(model.numShapes());
  std::vector<char> done(shapes_.size(), 0);
  for (int e = 0; e < mesh.numElements(); ++e) {
    const int k = model.shapeIndex(e);
    if (done[k]) continue;
    done[k] = 1;
    const auto X = mesh.elementCorners(e);
    const hex8::ElementReference& ref = model.reference(e);
    ShapeTables& t = shapes_[k];
    // The strain the element computes (its formulation's operator, hex8::strainOperator).
    t.centroid_B = hex8::strainOperator(X, ref, Vec3::Zero());
    for (int q = 0; q < 8; ++q) {
      const Mat3 J = X.transpose() * gt.grad[q];
      t.gauss_detJ[q] = J.determinant();
      t.gauss_B[q] = hex8::strainOperator(X, ref, gt.point[q]);
    }
  }
}

const std::vector<Mat3>& SprEstimator::rotations(const VecX& x, const std::vector<Eigen::Quaterniond>* guesses) const {
  for (auto& c : rotation_cache_)
    if (c.x.size() == x.size() && c.x.size() > 0 && c.x == x) return c.R;
  RotationCache& c = rotation_cache_[rotation_next_];
  rotation_next_ = 1 - rotation_next_;
  c.x = x;
  const int ne = model_.mesh().numElements();
  c.R.resize(ne);
  if (guesses)
    for (int e = 0; e < ne; ++e) c.R[e] = model_.computeRotation(e, x, (*guesses)[e]);
  else
    for (int e = 0; e < ne; ++e) c.R[e] = model_.computeRotation(e, x);
  return c.R;
}

Stress SprEstimator::elementStress(const VecX& x, int e, const Vec3& xi) const {
  return elementStress(x, e, xi, model_.computeRotation(e, x));
}

Eigen::Matrix<double, 24, 1> SprEstimator::corotatedDisplacement(const VecX& x, int e, const Mat3& R) const {
  const HexMesh& mesh = model_.mesh();
  const auto& el = mesh.element(e);
  // Corotated displacement relative to the centroid (as the model's forces).
  Vec3 xc = Vec3::Zero(), Xc = Vec3::Zero();
  for (int a = 0; a < 8; ++a) {
    xc += node3(x, el[a]);
    Xc += mesh.node(el[a]);
  }
  xc /= 8;
  Xc /= 8;
  Eigen::Matrix<double, 24, 1> u;
  for (int a = 0; a < 8; ++a) u.segment<3>(3 * a) = R.transpose() * (node3(x, el[a]) - xc) - (mesh.node(el[a]) - Xc);
  return u;
}

Stress SprEstimator::elementStress(const VecX& x, int e, const Vec3& xi, const Mat3& R) const {
  const auto u = corotatedDisplacement(x, e, R);
  const auto B = hex8::strainOperator(model_.mesh().elementCorners(e), model_.reference(e), xi);
  const Stress local = model_.materialInUse().elasticity() * (B * u);
  return rotate(R, local);
}

double SprEstimator::vonMises(const Stress& s) {
  return std::sqrt(0.5 * (std::pow(s[0] - s[1], 2) + std::pow(s[1] - s[2], 2) + std::pow(s[2] - s[0], 2)) +
                   3 * (s[3] * s[3] + s[4] * s[4] + s[5] * s[5]));
}

std::vector<Stress> SprEstimator::recover(const std::vector<Stress>& centroid) const {
  // Interior patches first, their polynomials also serve the patch's other nodes.
  const HexMesh& mesh = model_.mesh();
  const int nn = mesh.numNodes();
  std::vector<Stress> out(nn, Stress::Zero());
  std::vector<int> count(nn, 0);
  std::vector<Stress> borrowed(nn, Stress::Zero());
  std::vector<int> borrowed_count(nn, 0);
  for (int n = 0; n < nn; ++n) {
    if (!interior_[n]) continue;
    Eigen::Matrix<double, 4, 6> c = Eigen::Matrix<double, 4, 6>::Zero();
    const auto& F = fit_[n];
    for (size_t k = 0; k < node_elements_[n].size(); ++k)
      c.noalias() += F.col(static_cast<Eigen::Index>(k)) * centroid[node_elements_[n][k]].transpose();
    out[n] = c.row(0).transpose();
    count[n] = 1;
    for (int e : node_elements_[n])
      for (int a : mesh.element(e))
        if (!interior_[a]) {
          borrowed[a] += (c.row(0) + (mesh.node(a) - mesh.node(n)).transpose() * c.bottomRows<3>()).transpose();
          ++borrowed_count[a];
        }
  }
  for (int n = 0; n < nn; ++n) {
    if (count[n]) continue;
    if (borrowed_count[n]) {
      out[n] = borrowed[n] / borrowed_count[n];
    } else {  // no interior patch nearby (very coarse mesh): minimum-norm fit of its own patch
      std::vector<Vec3> pts;
      std::vector<Stress> vals;
      for (int e : node_elements_[n]) {
        pts.push_back(centroids_[e]);
        vals.push_back(centroid[e]);
      }
      Eigen::Matrix<double, 4, 6> c;
      fitLinear(pts, vals, mesh.node(n), c);
      out[n] = c.row(0).transpose();
    }
  }

  return out;
}

SprEstimator::DualIndicators SprEstimator::dual(const VecX& x, const VecX* reference, const ErrorEstimate& primal,
                                                const VecX& dz) const {
  const HexMesh& mesh = model_.mesh();
  const int ne = mesh.numElements();
  const auto& D = model_.materialInUse().elasticity();
  const Eigen::Matrix<double, 6, 6> Dinv = D.inverse();
  const std::vector<Mat3>& R = rotations(x);
  std::vector<Stress> centroid(ne);
  // The increment's element displacements in the rotated frames (the linearised corotational
  // strain of dz at x); the primal's as in estimate().
  std::vector<Eigen::Matrix<double, 24, 1>> zl(ne);
  for (int e = 0; e < ne; ++e) {
    const auto& el = mesh.element(e);
    for (int a = 0; a < 8; ++a) zl[e].segment<3>(3 * a) = R[e].transpose() * node3(dz, el[a]);
    centroid[e] = rotate(R[e], D * (shape(e).centroid_B * zl[e]));
  }
  const std::vector<Stress> zstar = recover(centroid);
  const GaussTable& gt = gaussTable();
  DualIndicators out;
  out.eta.assign(ne, 0.0);
  out.mixed.assign(ne, 0.0);
  double sum = 0;
  // The primal's sigma* - sigma_h at the Gauss points comes with its estimate (of x and
  // reference, as here).
  assert(primal.gauss_error.size() == static_cast<size_t>(ne));
  for (int e = 0; e < ne; ++e) {
    const auto& el = mesh.element(e);
    const ShapeTables& st = shape(e);
    const double frac = mesh.fraction(e);
    double eta2 = 0, mixed = 0;
    for (int q = 0; q < 8; ++q) {
      const double detJ = st.gauss_detJ[q] * frac;
      Stress zs = Stress::Zero();
      for (int a = 0; a < 8; ++a) zs += gt.shape[q][a] * zstar[el[a]];
      const Stress zh = rotate(R[e], D * (st.gauss_B[q] * zl[e]));
      const Stress& du = primal.gauss_error[e][q];
      const Stress dzs = zs - zh;
      eta2 += dzs.dot(Dinv * dzs) * detJ;
      mixed += du.dot(Dinv * dzs) * detJ;
    }
    out.eta[e] = std::sqrt(std::max(eta2, 0.0));
    out.mixed[e] = mixed;
    sum += eta2;
    out.mixed_total += mixed;
  }
  out.global = std::sqrt(sum);
  return out;
}

ErrorEstimate SprEstimator::estimate(const VecX& x, const VecX* reference,
                                     const std::vector<Eigen::Quaterniond>* guesses) const {
  const HexMesh& mesh = model_.mesh();
  const int ne = mesh.numElements();
  ErrorEstimate est;
  est.centroid_stress.resize(ne);
  const std::vector<Mat3>& R = rotations(x, guesses);
  static const std::vector<Mat3> none;
  const std::vector<Mat3>& R0 = reference ? rotations(*reference, guesses) : none;
  const auto& D0 = model_.materialInUse().elasticity();
  for (int e = 0; e < ne; ++e) {
    const auto& Bc = shape(e).centroid_B;
    est.centroid_stress[e] = rotate(R[e], D0 * (Bc * corotatedDisplacement(x, e, R[e])));
    if (reference) est.centroid_stress[e] -= rotate(R0[e], D0 * (Bc * corotatedDisplacement(*reference, e, R0[e])));
  }

  est.recovered = recover(est.centroid_stress);

  // Element errors in the energy norm (compliance D^-1), 2x2x2 Gauss.
  const auto& D = model_.materialInUse().elasticity();
  const Eigen::Matrix<double, 6, 6> Dinv = D.inverse();
  const GaussTable& gt = gaussTable();
  est.eta.assign(ne, 0.0);
  est.gauss_error.resize(ne);
  double sum = 0, energy = 0;
  for (int e = 0; e < ne; ++e) {
    const auto& el = mesh.element(e);
    const ShapeTables& st = shape(e);
    const Eigen::Matrix<double, 24, 1> u = corotatedDisplacement(x, e, R[e]);
    Eigen::Matrix<double, 24, 1> u0;
    if (reference) u0 = corotatedDisplacement(*reference, e, R0[e]);
    double eta2 = 0;
    // Only the material part of an immersed cell counts (its volume fraction).
    const double frac = mesh.fraction(e);
    for (int q = 0; q < 8; ++q) {
      const double detJ = st.gauss_detJ[q] * frac;
      Stress star = Stress::Zero();
      for (int a = 0; a < 8; ++a) star += gt.shape[q][a] * est.recovered[el[a]];
      const auto& B = st.gauss_B[q];
      Stress sh = rotate(R[e], D * (B * u));
      if (reference) sh -= rotate(R0[e], D * (B * u0));
      const Stress d = sh - star;
      est.gauss_error[e][q] = -d;
      eta2 += d.dot(Dinv * d) * detJ;
      energy += sh.dot(Dinv * sh) * detJ;
    }
    est.eta[e] = std::sqrt(std::max(eta2, 0.0));
    est.max = std::max(est.max, est.eta[e]);
    sum += eta2;
  }
  est.global = std::sqrt(sum);
  est.energy = std::sqrt(energy);
  return est;
}

}  // namespace needle_sim
