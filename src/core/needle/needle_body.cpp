#include "needle_sim/needle/needle_body.hpp"

#include <cmath>
#include <cstdio>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/needle/scene_trajectory.hpp"

namespace needle_sim {

namespace {

BeamSection sectionOf(const NeedleParameters& n) { return {n.radius, n.inner_radius}; }
BeamMaterial materialOf(const NeedleParameters& n) { return {n.young, n.poisson, n.density}; }

std::vector<char> basePrescribed(int dofs) {
  std::vector<char> p(dofs, 0);
  for (int i = 0; i < 6; ++i) p[i] = 1;
  return p;
}

ElementDofs beamElementDofs(int elements, const DofMap& dofs) {
  ElementDofs out;
  out.k = 12;
  for (int e = 0; e < elements; ++e)
    for (int i = 0; i < 12; ++i) out.add(dofs, 6 * e + i);
  return out;
}

// Residual weights: moments divided by the element length, so forces and moments compare.
double weightedNorm(const VecX& r_free, const DofMap& dofs, double L) {
  double s = 0;
  for (int k = 0; k < r_free.size(); ++k) {
    const double w = (dofs.freeToFull()[k] % 6) < 3 ? 1.0 : 1.0 / L;
    s += std::pow(w * r_free[k], 2);
  }
  return std::sqrt(s);
}
}  // namespace

NeedleBody::NeedleBody(const NeedleParameters& n, const SolverSettings& solver)
    : name_(n.name),
      beam_(n.elements, n.length, sectionOf(n), materialOf(n), n.base_position, n.base_direction),
      trajectory_(sceneTrajectory(n)),
      settings_(solver),
      dofs_(basePrescribed(6 * (n.elements + 1))),
      assembler_(dofs_.numFree(), beamElementDofs(n.elements, dofs_)),
      chol_(Ordering::Amd),
      bevel_(n.bevel) {
  state_ = beam_.restState();
  v_ = VecX::Zero(beam_.numDofs());
  mass_ = beam_.lumpedMass();
  dofs_.gather(mass_, mass_free_);
  f_ext_ = VecX::Zero(beam_.numDofs());
  for (int i = 0; i < beam_.numNodes(); ++i) f_ext_.segment<3>(6 * i) = mass_[6 * i] * n.gravity;
  const int tip = beam_.numNodes() - 1;
  f_ext_.segment<3>(6 * tip) += n.tip_force;
  f_ext_.segment<3>(6 * tip + 3) += n.tip_moment;
  Ke_.resize(beam_.numElements());
  placeAt(0.0);
}

void NeedleBody::basePoseAt(double t, Vec3& p, Eigen::Quaterniond& q) const {
  const BasePose pose = trajectory_.pose(t);
  p = pose.position;
  q = trajectory_.orientation(pose);
}

void NeedleBody::placeAt(double t) {
  Vec3 pb;
  Eigen::Quaterniond qb;
  basePoseAt(t, pb, qb);
  for (int i = 0; i < beam_.numNodes(); ++i) {
    state_.p[i] = pb + qb * (beam_.restPosition(i) - beam_.restPosition(0));
    state_.q[i] = qb;
  }
  v_.setZero();
}

Vec3 NeedleBody::tipDirection() const { return state_.q.back() * beam_.restDirection(); }

Eigen::Quaterniond NeedleBody::nodeFrame(int node) const {
  // The beam's node rotation carries the node's rest frame to its current one; the rest
  // frame in the command convention (command/pose_convention.hpp) is the rest base
  // orientation.
  const BasePose& rest = trajectory_.rest();
  const Eigen::Quaterniond rest_frame =
      Eigen::Quaterniond::FromTwoVectors(Vec3::UnitX(), rest.direction) * Eigen::AngleAxisd(rest.roll, Vec3::UnitX());
  return (state_.q[node] * rest_frame).normalized();
}

Vec3 NeedleBody::bevelDirection() const {
  const double a = bevel_.orientation;
  return nodeFrame(beam_.numNodes() - 1) * Vec3(0, std::cos(a), std::sin(a));
}

bool NeedleBody::assembleAndFactor(const std::vector<Mat12>& Ke, double c_m, double c_k, StepStats& st) {
  auto t0 = steadyNow();
  assembler_.setZero();
  for (int e = 0; e < beam_.numElements(); ++e) assembler_.addElement(e, Ke[e].data(), c_k);
  if (c_m != 0) assembler_.addDiagonal(mass_free_, c_m);
  st.assemble_ms += msSince(t0);
  t0 = steadyNow();
  if (!chol_.analyzed()) chol_.analyze(assembler_.matrix());
  const bool ok = chol_.factorize(assembler_.matrix());
  st.factor_ms += msSince(t0);
  st.factorizations += 1;
  return ok;
}

void NeedleBody::updateReaction(const VecX& base_accel) {
  // Internal force of the first element on the base node, at the current state.
  const Vec12 fe = beam_.elementForce(state_, 0);
  base_force_ = mass_[0] * base_accel.head<3>() - fe.segment<3>(0) - f_ext_.segment<3>(0);
  base_moment_ = mass_[3] * base_accel.tail<3>() - fe.segment<3>(3) - f_ext_.segment<3>(3);
}

StepStats NeedleBody::stepDynamic(double t, double h) {
  StepStats st = freeMotion(t, h);
  commit(t, h);
  return st;
}

StepStats NeedleBody::freeMotion(double t, double h) {
  StepStats st;
  auto t0 = steadyNow();
  const double alpha = settings_.rayleigh_mass, beta = settings_.rayleigh_stiffness;
  const double c_m = 1 + h * alpha, c_k = h * beta + h * h;
  const int n = beam_.numDofs(), ne = beam_.numElements();

  // Base: the velocity that lands exactly on the commanded pose at t + h.
  basePoseAt(t + h, base_target_p_, base_target_q_);
  dv_ = VecX::Zero(n);
  dv_.segment<3>(0) = (base_target_p_ - state_.p[0]) / h - v_.segment<3>(0);
  dv_.segment<3>(3) = quaternionLog(base_target_q_ * state_.q[0].conjugate()) / h - v_.segment<3>(3);

  // rhs = h (f - (h + beta) K v - alpha M v) - c_k K dv_base
  VecX rhs;
  beam_.internalForce(state_, rhs);
  rhs += f_ext_;
  rhs.array() -= alpha * mass_.array() * v_.array();
  rhs *= h;
  for (int e = 0; e < ne; ++e) {
    beam_.elementStiffness(state_, e, Ke_[e]);
    Vec12 w = (-h * (h + beta)) * v_.segment<12>(6 * e);
    if (e == 0) w.head<6>() -= c_k * dv_.head<6>();
    rhs.segment<12>(6 * e).noalias() += Ke_[e] * w;
  }
  VecX b, dv_free;
  dofs_.gather(rhs, b);
  st.forces_ms = msSince(t0);

  if (!assembleAndFactor(Ke_, c_m, c_k, st))
    throw NumericalError(-1, "needle '" + name_ + "': system matrix is not positive definite");
  t0 = steadyNow();
  chol_.solve(b, dv_free);
  for (int k = 0; k < dofs_.numFree(); ++k) dv_[dofs_.freeToFull()[k]] = dv_free[k];
  st.solve_ms = msSince(t0);
  return st;
}

void NeedleBody::addVelocityChangeFree(const VecX& d) {
  for (int k = 0; k < dofs_.numFree(); ++k) dv_[dofs_.freeToFull()[k]] += d[k];
}

void NeedleBody::complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C) {
  const auto k = static_cast<Eigen::Index>(free_dofs.size());
  Eigen::MatrixXd E = Eigen::MatrixXd::Zero(dofs_.numFree(), k);
  for (Eigen::Index j = 0; j < k; ++j) E(free_dofs[j], j) = 1.0;
  chol_.solve(E, columns_);
  C.resize(k, k);
  for (Eigen::Index i = 0; i < k; ++i) C.row(i) = columns_.row(free_dofs[i]);
}

void NeedleBody::addInverseColumns(const std::vector<int>& free_dofs, const VecX& c) {
  addVelocityChangeFree(columns_ * c);
}

void NeedleBody::commit(double /*t*/, double h) {
  v_ += dv_;
  BeamState& s = state_;
  for (int i = 1; i < beam_.numNodes(); ++i) {
    s.p[i] += h * v_.segment<3>(6 * i);
    s.q[i] = (quaternionExp(h * v_.segment<3>(6 * i + 3)) * s.q[i]).normalized();
  }
  s.p[0] = base_target_p_;  // exactly on the command, no drift
  s.q[0] = base_target_q_;
  updateReaction(dv_.head<6>() / h);
  if (!v_.allFinite()) throw NumericalError(-1, "needle '" + name_ + "': non-finite velocities");
}

StepStats NeedleBody::solveStatic(double t) {
  StepStats st;
  // Start from the current shape carried rigidly by the base's motion since the last solve.
  Vec3 pc;
  Eigen::Quaterniond qc;
  basePoseAt(t, pc, qc);
  const Eigen::Quaterniond dq = qc * state_.q[0].conjugate();
  const Vec3 p0 = state_.p[0];
  for (int i = 0; i < beam_.numNodes(); ++i) {
    state_.p[i] = pc + dq * (state_.p[i] - p0);
    state_.q[i] = (dq * state_.q[i]).normalized();
  }
  v_.setZero();
  const double L = beam_.elementLength(), tol = settings_.static_tolerance;
  VecX r, r_free, d_free, d = VecX::Zero(beam_.numDofs());
  VecX fe_free;
  dofs_.gather(f_ext_, fe_free);
  double ref = weightedNorm(fe_free, dofs_, L);
  for (int it = 0; it <= settings_.static_max_iterations; ++it) {
    auto t0 = steadyNow();
    beam_.internalForce(state_, r);
    r += f_ext_;
    dofs_.gather(r, r_free);
    const double rn = weightedNorm(r_free, dofs_, L);
    if (it == 0) ref = std::max(ref, rn);
    st.newton_residual = ref > 0 ? rn / ref : 0;
    if (!std::isfinite(rn)) throw NumericalError(-1, "needle '" + name_ + "': static residual is NaN/Inf");
    // Also stop when the Newton correction is at round-off level (residual floor).
    double dn = 0;
    for (int k = 0; k < d_free.size(); ++k) dn += std::pow((dofs_.freeToFull()[k] % 6 < 3 ? 1.0 : L) * d_free[k], 2);
    if (rn <= tol * ref || ref == 0 || (it > 0 && std::sqrt(dn) <= 1e-13 * beam_.length())) {
      st.newton_iterations = it;
      st.forces_ms += msSince(t0);
      updateReaction(VecX::Zero(6));
      return st;
    }
    if (it == settings_.static_max_iterations) break;
    // Consistent tangent; where it is not positive definite (far from equilibrium, or
    // compressed), the material tangent, which always is (a modified Newton step).
    for (int e = 0; e < beam_.numElements(); ++e) beam_.elementConsistentStiffness(state_, e, Ke_[e]);
    st.forces_ms += msSince(t0);
    if (!assembleAndFactor(Ke_, 0.0, 1.0, st)) {
      for (int e = 0; e < beam_.numElements(); ++e) beam_.elementStiffness(state_, e, Ke_[e]);
      if (!assembleAndFactor(Ke_, 0.0, 1.0, st))
        throw NumericalError(-1, "needle '" + name_ + "': stiffness matrix is not positive definite");
    }
    t0 = steadyNow();
    chol_.solve(r_free, d_free);
    // Limit the largest nodal rotation per iteration to 0.5 rad (a damped Newton step far
    // from equilibrium, e.g. the first step under a large load).
    double max_rot = 0;
    for (int k = 0; k < d_free.size(); ++k)
      if (dofs_.freeToFull()[k] % 6 >= 3) max_rot = std::max(max_rot, std::abs(d_free[k]));
    if (max_rot > 0.5) d_free *= 0.5 / max_rot;
    dofs_.scatter(d_free, d);
    CorotationalBeam::applyIncrement(state_, d);
    st.solve_ms += msSince(t0);
  }
  char msg[160];
  std::snprintf(msg, sizeof msg, "needle '%s': static solve did not converge in %d Newton iterations (relative residual %.3e)",
                name_.c_str(), settings_.static_max_iterations, st.newton_residual);
  throw NumericalError(-1, msg);
}

}  // namespace needle_sim
