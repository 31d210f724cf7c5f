#include "needle_sim/fem/corotational_hex_model.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <Eigen/Cholesky>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>

namespace needle_sim {

namespace {

// Key identifying an element's rest shape up to translation, quantised to 1e-10 of the
// mesh size, so that identical grid cells share one reference.
// The volume fraction (immersed geometry) is part of the key: it scales K0 and the volumes.
using ReferenceKey = std::pair<hex8::ShapeKey, long long>;
ReferenceKey referenceKey(const Eigen::Matrix<double, 8, 3>& X, double quantum, double fraction) {
  return {hex8::shapeKey(X, quantum), std::llround(fraction * 1e12)};
}

// Rotation R maximising tr(R^T A) (the rotation of the polar decomposition A = R U when
// det A > 0), updating q in place. Each iteration turns R by omega in the world frame.
// Mueller et al. (2016) take omega = g / |tr(S)| with the gradient g = sum_i r_i x a_i and
// S = sym(A R^T); near the solution this converges only linearly (factor 1/3 for A ~ I).
// We take the Newton step omega = (tr(S) I - S)^-1 g when that Hessian is positive
// definite (quadratic convergence), and Mueller's step otherwise (inverted or flat
// elements), which always keeps R a proper rotation.
void extractRotation(const Mat3& A, Eigen::Quaterniond& q) {
  for (int it = 0; it < 40; ++it) {
    const Mat3 R = q.toRotationMatrix();
    const Vec3 g = R.col(0).cross(A.col(0)) + R.col(1).cross(A.col(1)) + R.col(2).cross(A.col(2));
    const Mat3 B = A * R.transpose();
    const Mat3 S = 0.5 * (B + B.transpose());
    const double tr = S.trace();
    Vec3 omega;
    const Mat3 H = tr * Mat3::Identity() - S;
    Eigen::LLT<Mat3> llt(H);
    if (tr > 0 && llt.info() == Eigen::Success && H.diagonal().minCoeff() > 1e-6 * tr)
      omega = llt.solve(g);
    else
      omega = g / (std::abs(tr) + 1e-9);
    const double w = omega.norm();
    if (!(w >= 1e-15)) break;  // converged (also stops on NaN)
    q = Eigen::Quaterniond(Eigen::AngleAxisd(std::min(w, 1.0), omega / w)) * q;
    q.normalize();
    if (w < 1e-9) break;  // a Newton step this small has converged to round-off
  }
}

}  // namespace

CorotationalHexModel::CorotationalHexModel(const CorotationalHexModel& o, const HexMesh& mesh)
    : mesh_(mesh),
      material_(o.material_),
      stiffness_scale_(o.stiffnessScale()),
      refs_(o.refs_),
      ref_of_(o.ref_of_),
      shape_of_(o.shape_of_),
      num_shapes_(o.num_shapes_),
      quat_(o.quat_),
      rot_(o.rot_),
      nodal_volume_(o.nodal_volume_),
      inverted_(o.inverted_) {
  assert(mesh.numElements() == o.mesh_.numElements() && mesh.numNodes() == o.mesh_.numNodes());
}

CorotationalHexModel::CorotationalHexModel(const HexMesh& mesh, const LinearElasticMaterial& material)
    : mesh_(mesh), material_(material) {
  // Elements of one rest shape and volume fraction share a reference; the reference of each
  // shape is computed once, and the cut cells of an immersed grid (hundreds of fractions, a
  // few shapes) scale a copy of it. The keys first, so that refs_ is allocated once (4.6 kB
  // a reference: growing it cost the adaptive DBS pre-step 10-20 ms a mesh).
  std::map<ReferenceKey, int> index;
  std::map<hex8::ShapeKey, int> shapes;
  std::vector<int> first;  // an element of each reference
  ref_of_.resize(mesh.numElements());
  shape_of_.resize(mesh.numElements());
  const double quantum = 1e-10 * std::max((mesh.boundsMax() - mesh.boundsMin()).norm(), 1e-300);
  for (int e = 0; e < mesh.numElements(); ++e) {
    const ReferenceKey key = referenceKey(mesh.elementCorners(e), quantum, mesh.fraction(e));
    shape_of_[e] = shapes.try_emplace(key.first, static_cast<int>(shapes.size())).first->second;
    const auto [it, fresh] = index.try_emplace(key, static_cast<int>(first.size()));
    if (fresh) first.push_back(e);
    ref_of_[e] = it->second;
  }
  num_shapes_ = static_cast<int>(shapes.size());
  std::vector<std::optional<hex8::ElementReference>> unit(num_shapes_);
  refs_.reserve(first.size());
  for (int e : first) {
    auto& shape = unit[shape_of_[e]];
    if (!shape) {
      try {
        shape = hex8::computeReference(mesh.elementCorners(e), material);
      } catch (const std::invalid_argument&) {
        throw std::invalid_argument("element " + std::to_string(e) + " is degenerate or inverted at rest");
      }
    }
    auto& r = refs_.emplace_back(*shape);
    const double frac = mesh.fraction(e);
    if (frac != 1.0) {
      r.K0 *= frac;
      r.node_volume *= frac;
      r.volume *= frac;
    }
  }
  nodal_volume_ = VecX::Zero(mesh.numNodes());
  for (int e = 0; e < mesh.numElements(); ++e)
    for (int a = 0; a < 8; ++a) nodal_volume_[mesh.element(e)[a]] += refs_[ref_of_[e]].node_volume[a];
  quat_.assign(mesh.numElements(), Eigen::Quaterniond::Identity());
  rot_.assign(mesh.numElements(), Mat3::Identity());
}

void CorotationalHexModel::resetRotations() {
  quat_.assign(mesh_.numElements(), Eigen::Quaterniond::Identity());
  rot_.assign(mesh_.numElements(), Mat3::Identity());
  inverted_ = 0;
}

Mat3 CorotationalHexModel::deformationGradient(int e, const VecX& x) const {
  const auto& el = mesh_.element(e);
  const auto& G = refs_[ref_of_[e]].grad_centroid;
  Mat3 F = Mat3::Zero();
  for (int a = 0; a < 8; ++a) F.noalias() += node3(x, el[a]) * G.row(a);
  return F;
}

void CorotationalHexModel::updateRotations(const VecX& x) {
  assert(x.size() == mesh_.numDofs());
  int inverted = 0;
  for (int e = 0; e < mesh_.numElements(); ++e) {
    const Mat3 F = deformationGradient(e, x);
    if (!(F.determinant() > 0)) ++inverted;
    extractRotation(F, quat_[e]);
    rot_[e] = quat_[e].toRotationMatrix();
  }
  inverted_ = inverted;
}

Mat3 CorotationalHexModel::computeRotation(int e, const VecX& x) const { return computeRotation(e, x, quat_[e]); }

Mat3 CorotationalHexModel::computeRotation(int e, const VecX& x, const Eigen::Quaterniond& guess) const {
  Eigen::Quaterniond q = guess;
  extractRotation(deformationGradient(e, x), q);
  return q.toRotationMatrix();
}

namespace {
// K0 v for one element, as a sum of K0's columns: Eigen's general matrix-vector kernel,
// which a fixed 24x24 product goes through, costs 30 % more here (1,500 products 0.126
// against 0.090 ms without -march; these products are a fifth of a DBS step).
inline Eigen::Matrix<double, 24, 1> timesK0(const hex8::Mat24& K0, const Eigen::Matrix<double, 24, 1>& v) {
  Eigen::Matrix<double, 24, 1> w = K0.col(0) * v[0];
  for (int j = 1; j < 24; ++j) w.noalias() += K0.col(j) * v[j];
  return w;
}
}  // namespace

Eigen::Matrix<double, 24, 1> CorotationalHexModel::localDisplacement(int e, const VecX& x) const {
  // Relative to the element centroid: identical in exact arithmetic (K0 ignores
  // translations) but free of the cancellation of R^T x - X when |x| >> |u|.
  const auto& el = mesh_.element(e);
  const Mat3& R = rot_[e];
  Vec3 xc = Vec3::Zero(), Xc = Vec3::Zero();
  for (int a = 0; a < 8; ++a) {
    xc += node3(x, el[a]);
    Xc += mesh_.node(el[a]);
  }
  xc /= 8;
  Xc /= 8;
  Eigen::Matrix<double, 24, 1> u;
  for (int a = 0; a < 8; ++a)
    u.segment<3>(3 * a).noalias() = R.transpose() * (node3(x, el[a]) - xc) - (mesh_.node(el[a]) - Xc);
  return u;
}

// The stiffness scale is applied only when it is not 1, so that a run without an adopted
// stiffness computes what it did before it existed, bit for bit.
void CorotationalHexModel::addInternalForce(const VecX& x, VecX& f) const {
  const double k = stiffnessScale();
  for (int e = 0; e < mesh_.numElements(); ++e) {
    Eigen::Matrix<double, 24, 1> fl = timesK0(refs_[ref_of_[e]].K0, localDisplacement(e, x));
    if (k != 1.0) fl *= k;
    const auto& el = mesh_.element(e);
    const Mat3& R = rot_[e];
    for (int a = 0; a < 8; ++a) node3(f, el[a]).noalias() -= R * fl.segment<3>(3 * a);
  }
}

void CorotationalHexModel::addStiffnessProduct(const VecX& v, double s, VecX& out) const {
  s *= stiffnessScale();
  Eigen::Matrix<double, 24, 1> vl;
  for (int e = 0; e < mesh_.numElements(); ++e) {
    const auto& el = mesh_.element(e);
    const Mat3& R = rot_[e];
    for (int a = 0; a < 8; ++a) vl.segment<3>(3 * a).noalias() = R.transpose() * node3(v, el[a]);
    const Eigen::Matrix<double, 24, 1> w = timesK0(refs_[ref_of_[e]].K0, vl);
    for (int a = 0; a < 8; ++a) node3(out, el[a]).noalias() += s * (R * w.segment<3>(3 * a));
  }
}

void CorotationalHexModel::elementStiffness(int e, const Mat3& R, hex8::Mat24& Ke) const {
  const auto& K0 = refs_[ref_of_[e]].K0;
  for (int a = 0; a < 8; ++a)
    for (int b = 0; b < 8; ++b)
      Ke.block<3, 3>(3 * a, 3 * b).noalias() = R * K0.block<3, 3>(3 * a, 3 * b) * R.transpose();
  const double k = stiffnessScale();
  if (k != 1.0) Ke *= k;
}

void CorotationalHexModel::rotationTerms(const VecX& x, RotationTerms& t) const {
  const int n = mesh_.numElements();
  t.h_inv.resize(n);
  t.force.resize(n);
  t.centred.resize(n);
  const double k = stiffnessScale();
  for (int e = 0; e < n; ++e) {
    const auto& el = mesh_.element(e);
    const Mat3& R = rot_[e];
    Vec3 xc = Vec3::Zero();
    for (int a = 0; a < 8; ++a) xc += node3(x, el[a]);
    xc /= 8;
    const Mat3 B = deformationGradient(e, x) * R.transpose();
    const Mat3 S = 0.5 * (B + B.transpose());
    const Mat3 H = S.trace() * Mat3::Identity() - S;
    // Where the extraction itself could not take Newton steps (flat or inverted elements)
    // the derivative is not defined: those elements keep the plain tangent.
    Eigen::LLT<Mat3> llt(H);
    const bool ok = S.trace() > 0 && llt.info() == Eigen::Success && H.diagonal().minCoeff() > 1e-6 * S.trace();
    t.h_inv[e] = ok ? Mat3(llt.solve(Mat3::Identity())) : Mat3::Zero();
    Eigen::Matrix<double, 24, 1> fl = timesK0(refs_[ref_of_[e]].K0, localDisplacement(e, x));
    if (k != 1.0) fl *= k;
    for (int a = 0; a < 8; ++a) {
      t.force[e].segment<3>(3 * a) = R * fl.segment<3>(3 * a);
      t.centred[e].segment<3>(3 * a) = node3(x, el[a]) - xc;
    }
  }
}

void CorotationalHexModel::addRotationStiffnessProduct(const RotationTerms& t, const VecX& v, double s,
                                                        VecX& out) const {
  const double ks = stiffnessScale();
  Eigen::Matrix<double, 24, 1> y;
  for (int e = 0; e < mesh_.numElements(); ++e) {
    if (t.h_inv[e].isZero(0)) continue;
    const auto& el = mesh_.element(e);
    const auto& G = refs_[ref_of_[e]].grad_centroid;
    const Mat3& R = rot_[e];
    Vec3 g = Vec3::Zero();
    for (int a = 0; a < 8; ++a) g += (R * G.row(a).transpose()).cross(node3(v, el[a]));
    const Vec3 w = t.h_inv[e] * g;
    for (int b = 0; b < 8; ++b) y.segment<3>(3 * b).noalias() = R.transpose() * w.cross(t.centred[e].segment<3>(3 * b));
    Eigen::Matrix<double, 24, 1> k = timesK0(refs_[ref_of_[e]].K0, y);
    if (ks != 1.0) k *= ks;
    for (int a = 0; a < 8; ++a)
      node3(out, el[a]).noalias() += s * (w.cross(t.force[e].segment<3>(3 * a)) - R * k.segment<3>(3 * a));
  }
}

double CorotationalHexModel::elasticEnergy(const VecX& x) const {
  double E = 0;
  for (int e = 0; e < mesh_.numElements(); ++e) {
    const auto u = localDisplacement(e, x);
    E += 0.5 * u.dot(refs_[ref_of_[e]].K0 * u);
  }
  const double k = stiffnessScale();
  return k != 1.0 ? k * E : E;
}

}  // namespace needle_sim
