#pragma once
// A needle as a body of the simulation: the corotational beam, its driven base, loads,
// state and linear solver.
//
// Dynamic step: the same linearised implicit Euler as the tissue,
//   (M + hC + h^2 K) dv = h (f + f_ext - hKv - Cv),  C = alpha M + beta K,
// where the base node's velocity change is known (it must arrive exactly at the commanded
// pose at t + h) and moved to the right-hand side: A_ff dv_f = b_f - A_fp dv_p. Positions
// update p += h v, orientations q <- exp(h omega) q. The base reaction (force and moment
// the holder applies to the needle) is m a - f_internal - f_external at the base node.
// Static solve: Newton with the consistent tangent, base at the commanded pose.
#include <memory>
#include <vector>

#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/needle/corotational_beam.hpp"
#include "needle_sim/core/step_stats.hpp"
#include "needle_sim/needle/needle_parameters.hpp"
#include "needle_sim/solver/cholmod_solver.hpp"
#include "needle_sim/solver/solver_settings.hpp"
#include "needle_sim/solver/dof_map.hpp"
#include "needle_sim/solver/symmetric_assembler.hpp"

namespace needle_sim {

class NeedleBody {
 public:
  NeedleBody(const NeedleParameters& needle, const SolverSettings& solver);

  const std::string& name() const { return name_; }
  const CorotationalBeam& beam() const { return beam_; }
  const BeamState& state() const { return state_; }
  const VecX& velocities() const { return v_; }  // 6 per node: linear, angular (world)
  BaseTrajectory& trajectory() { return trajectory_; }
  const BaseTrajectory& trajectory() const { return trajectory_; }
  int numDofs() const { return beam_.numDofs(); }

  // Places the needle rigidly at the commanded pose of time t (no internal force).
  void placeAt(double t);
  // Advances from time t to t + h: freeMotion + (constraint corrections) + commit.
  StepStats stepDynamic(double t, double h);
  // Solves the implicit Euler system without constraints (base on its command); nothing
  // moves until commit().
  StepStats freeMotion(double t, double h);
  // Velocity change of all DOFs (6 per node) after freeMotion, plus corrections.
  const VecX& velocityChange() const { return dv_; }
  const DofMap& dofs() const { return dofs_; }
  void addVelocityChangeFree(const VecX& d);
  void commit(double t, double h);
  // C = [A^-1]_{S,S} for the given free DOFs, from this step's factorisation, and the
  // correction dv_free += A^-1 E_S c with the same columns.
  void complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C);
  void addInverseColumns(const std::vector<int>& free_dofs, const VecX& c);
  // Equilibrium with the base at the pose commanded for time t.
  StepStats solveStatic(double t);

  // Orientation of beam node `node` in the pose convention (x along the needle; at rest the
  // base's rest orientation; command/pose_convention.hpp).
  Eigen::Quaterniond nodeFrame(int node) const;
  const BevelParameters& bevel() const { return bevel_; }
  // The bevel's lateral direction (world): the tip frame's y axis turned by the bevel's
  // orientation (needle_parameters.hpp).
  Vec3 bevelDirection() const;
  Vec3 tipPosition() const { return state_.p.back(); }
  Vec3 tipDirection() const;
  const Vec3& baseForce() const { return base_force_; }
  const Vec3& baseMoment() const { return base_moment_; }
  double kineticEnergy() const { return 0.5 * (mass_.array() * v_.array().square()).sum(); }
  double elasticEnergy() const { return beam_.elasticEnergy(state_); }

  // Sets the state (tests, restarts).
  void setState(const BeamState& s, const VecX& v) {
    state_ = s;
    v_ = v;
  }

 private:
  void basePoseAt(double t, Vec3& p, Eigen::Quaterniond& q) const;
  void updateReaction(const VecX& base_accel);
  bool assembleAndFactor(const std::vector<Mat12>& Ke, double c_m, double c_k, StepStats& st);

  std::string name_;
  CorotationalBeam beam_;
  BaseTrajectory trajectory_;
  SolverSettings settings_;
  BeamState state_;
  VecX v_, mass_, mass_free_, f_ext_;
  DofMap dofs_;
  SymmetricAssembler assembler_;
  CholmodSolver chol_;
  std::vector<Mat12> Ke_;
  VecX dv_;
  Eigen::MatrixXd columns_;  // A^-1 E_S of the last complianceBlock
  Vec3 base_target_p_ = Vec3::Zero();
  Eigen::Quaterniond base_target_q_ = Eigen::Quaterniond::Identity();
  Vec3 base_force_ = Vec3::Zero(), base_moment_ = Vec3::Zero();
  BevelParameters bevel_;
};

}  // namespace needle_sim
