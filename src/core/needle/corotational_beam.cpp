#include "needle_sim/needle/corotational_beam.hpp"

#include <cassert>
#include <cmath>
#include <stdexcept>

namespace needle_sim {

double BeamSection::area() const { return M_PI * (std::pow(outer_radius, 2) - std::pow(inner_radius, 2)); }
double BeamSection::secondMoment() const { return M_PI / 4 * (std::pow(outer_radius, 4) - std::pow(inner_radius, 4)); }
double BeamSection::polarMoment() const { return 2 * secondMoment(); }

Vec3 quaternionLog(const Eigen::Quaterniond& q_in) {
  Eigen::Quaterniond q = q_in;
  if (q.w() < 0) q.coeffs() = -q.coeffs();  // shortest rotation
  const double n = q.vec().norm();
  if (n < 1e-300) return Vec3::Zero();
  const double angle = 2 * std::atan2(n, q.w());
  return q.vec() * (angle / n);
}

Eigen::Quaterniond quaternionExp(const Vec3& v) {
  const double a = v.norm();
  if (a < 1e-12) {
    // Second-order series keeps exp accurate and unit for tiny rotations.
    Eigen::Quaterniond q(1.0 - a * a / 8, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]);
    return q.normalized();
  }
  const double s = std::sin(a / 2) / a;
  return Eigen::Quaterniond(std::cos(a / 2), s * v[0], s * v[1], s * v[2]);
}

CorotationalBeam::CorotationalBeam(int elements, double length, const BeamSection& section,
                                   const BeamMaterial& material, const Vec3& base, const Vec3& direction)
    : length_(length), L0_(length / elements), section_(section), material_(material), dir0_(direction.normalized()) {
  if (elements < 1 || !(length > 0)) throw std::invalid_argument("CorotationalBeam: bad size");
  // Rest frame: axis plus any perpendicular pair.
  Vec3 n = dir0_.unitOrthogonal();
  Mat3 E0;
  E0.col(0) = dir0_;
  E0.col(1) = n;
  E0.col(2) = dir0_.cross(n);
  qE0_ = Eigen::Quaterniond(E0).normalized();
  for (int i = 0; i <= elements; ++i) rest_.push_back(base + dir0_ * (L0_ * i));
  EA_ = material.young * section.area();
  GJ_ = material.shearModulus() * section.polarMoment();
  EI_ = material.young * section.secondMoment();
  Kloc_ = localStiffness();
}

BeamState CorotationalBeam::restState() const {
  BeamState s;
  s.p = rest_;
  s.q.assign(rest_.size(), Eigen::Quaterniond::Identity());
  return s;
}

Eigen::Matrix<double, 12, 12> CorotationalBeam::localStiffness() const {
  // DOF order: u_a (x,y,z), phi_a (x,y,z), u_b, phi_b; x along the element.
  Mat12 K = Mat12::Zero();
  const double L = L0_, L2 = L * L, L3 = L2 * L;
  auto add = [&](int i, int j, double v) { K(i, j) += v; };
  const double a = EA_ / L, t = GJ_ / L;
  add(0, 0, a); add(6, 6, a); add(0, 6, -a); add(6, 0, -a);
  add(3, 3, t); add(9, 9, t); add(3, 9, -t); add(9, 3, -t);
  // bending in the x-y plane: (u_y, phi_z)
  const int y[4] = {1, 5, 7, 11};
  const double ky[4][4] = {{12, 6 * L, -12, 6 * L}, {6 * L, 4 * L2, -6 * L, 2 * L2},
                           {-12, -6 * L, 12, -6 * L}, {6 * L, 2 * L2, -6 * L, 4 * L2}};
  // bending in the x-z plane: (u_z, phi_y), opposite coupling sign
  const int z[4] = {2, 4, 8, 10};
  const double kz[4][4] = {{12, -6 * L, -12, -6 * L}, {-6 * L, 4 * L2, 6 * L, 2 * L2},
                           {-12, 6 * L, 12, 6 * L}, {-6 * L, 2 * L2, 6 * L, 4 * L2}};
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) {
      add(y[i], y[j], EI_ / L3 * ky[i][j]);
      add(z[i], z[j], EI_ / L3 * kz[i][j]);
    }
  return K;
}

CorotationalBeam::Local CorotationalBeam::local(const BeamState& s, int e) const {
  return local(s.p[e], s.q[e], s.p[e + 1], s.q[e + 1]);
}

CorotationalBeam::Local CorotationalBeam::local(const Vec3& pa, const Eigen::Quaterniond& qa, const Vec3& pb,
                                                const Eigen::Quaterniond& qb) const {
  Local o;
  const Vec3 d = pb - pa;
  o.l = d.norm();
  o.e1 = d / o.l;
  // Mean rotation of the two nodes, carried rest frame, then aligned with the chord.
  const Eigen::Quaterniond qm = qa * Eigen::Quaterniond::Identity().slerp(0.5, qa.conjugate() * qb);
  const Eigen::Quaterniond qf = qm * qE0_;
  const Vec3 f1 = qf * Vec3::UnitX();
  o.qe = (Eigen::Quaterniond::FromTwoVectors(f1, o.e1) * qf).normalized();
  const Eigen::Quaterniond qec = o.qe.conjugate();
  o.ta = quaternionLog(qec * qa * qE0_);
  o.tb = quaternionLog(qec * qb * qE0_);
  return o;
}

Vec12 CorotationalBeam::elementForce(const BeamState& s, int e) const { return elementForce(local(s, e)); }

Vec12 CorotationalBeam::elementForce(const Local& o) const {
  const double N = EA_ / L0_ * (o.l - L0_);
  const double T = GJ_ / L0_ * (o.tb.x() - o.ta.x());
  const double k = EI_ / L0_;
  const Vec3 ma(-T, k * (4 * o.ta.y() + 2 * o.tb.y()), k * (4 * o.ta.z() + 2 * o.tb.z()));
  const Vec3 mb(T, k * (2 * o.ta.y() + 4 * o.tb.y()), k * (2 * o.ta.z() + 4 * o.tb.z()));
  const Mat3 Re = o.qe.toRotationMatrix();
  // Gradient of the energy; the chord's spin couples the bending moments to the lateral
  // translations (shear force (Ma + Mb) / l).
  const Vec3 g_pb = N * o.e1 + (ma.y() + mb.y()) / o.l * Re.col(2) - (ma.z() + mb.z()) / o.l * Re.col(1);
  Vec12 f;
  f.segment<3>(0) = g_pb;
  f.segment<3>(3) = -(Re * ma);
  f.segment<3>(6) = -g_pb;
  f.segment<3>(9) = -(Re * mb);
  return f;
}

void CorotationalBeam::internalForce(const BeamState& s, VecX& f) const {
  f.setZero(numDofs());
  for (int e = 0; e < numElements(); ++e) f.segment<12>(6 * e) += elementForce(s, e);
}

void CorotationalBeam::elementStiffness(const BeamState& s, int e, Mat12& K) const {
  const Mat3 R = local(s, e).qe.toRotationMatrix();
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) K.block<3, 3>(3 * i, 3 * j).noalias() = R * Kloc_.block<3, 3>(3 * i, 3 * j) * R.transpose();
}

void CorotationalBeam::elementConsistentStiffness(const BeamState& s, int e, Mat12& K) const {
  for (int j = 0; j < 12; ++j) {
    const int node = j / 6, comp = j % 6;
    const double h = comp < 3 ? 1e-7 * L0_ : 1e-7;
    Vec12 f[2];
    for (int k = 0; k < 2; ++k) {
      const double step = k == 0 ? h : -h;
      Vec3 p[2] = {s.p[e], s.p[e + 1]};
      Eigen::Quaterniond q[2] = {s.q[e], s.q[e + 1]};
      if (comp < 3)
        p[node][comp] += step;
      else
        q[node] = (quaternionExp(Vec3::Unit(comp - 3) * step) * q[node]).normalized();
      f[k] = elementForce(local(p[0], q[0], p[1], q[1]));
    }
    K.col(j) = -(f[0] - f[1]) / (2 * h);
  }
  K = (0.5 * (K + K.transpose())).eval();
}

double CorotationalBeam::elasticEnergy(const BeamState& s) const {
  double E = 0;
  const double k = EI_ / L0_;
  for (int e = 0; e < numElements(); ++e) {
    const Local o = local(s, e);
    const double u = o.l - L0_, tw = o.tb.x() - o.ta.x();
    E += 0.5 * EA_ / L0_ * u * u + 0.5 * GJ_ / L0_ * tw * tw;
    E += k * (2 * o.ta.y() * o.ta.y() + 2 * o.ta.y() * o.tb.y() + 2 * o.tb.y() * o.tb.y());
    E += k * (2 * o.ta.z() * o.ta.z() + 2 * o.ta.z() * o.tb.z() + 2 * o.tb.z() * o.tb.z());
  }
  return E;
}

VecX CorotationalBeam::lumpedMass() const {
  VecX m = VecX::Zero(numDofs());
  const double rho = material_.density;
  const double mt = rho * section_.area() * L0_ / 2, mr = rho * section_.polarMoment() * L0_ / 2;
  for (int e = 0; e < numElements(); ++e)
    for (int n : {e, e + 1}) {
      m.segment<3>(6 * n).array() += mt;
      m.segment<3>(6 * n + 3).array() += mr;
    }
  return m;
}

void CorotationalBeam::applyIncrement(BeamState& s, const VecX& d) {
  for (size_t i = 0; i < s.p.size(); ++i) {
    s.p[i] += d.segment<3>(6 * i);
    s.q[i] = (quaternionExp(d.segment<3>(6 * i + 3)) * s.q[i]).normalized();
  }
}

}  // namespace needle_sim
