#pragma once
// The deformable tissue as a body of the simulation: mesh, corotational model, boundary
// conditions, loads, state (x, v) and its linear solver (doc/method.md, "Tissue" and
// "Time integration"). Its pieces live beside it: boundary conditions and loads
// (tissue_loads.hpp), the static Newton with load control (static_newton.cpp,
// load_control.hpp), the compliance columns (compliance_cache.hpp).
//
// Dynamic step (linearised implicit Euler, Baraff & Witkin 1998), with K = -df/dx and
// Rayleigh damping C = alpha M + beta K:
//   (M + h C + h^2 K) dv = h ( f(x) + f_ext - h K v - C v ),   v += dv,   x += h v.
// Static solve: Newton on the corotational forces, K(x) dx = f(x) + f_ext, to equilibrium.
// Prescribed DOFs keep their position and zero velocity; they are not unknowns.
#include <algorithm>
#include <functional>
#include <memory>
#include <optional>
#include <unordered_map>
#include <vector>

#include "needle_sim/core/step_stats.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/solver/dof_map.hpp"
#include "needle_sim/solver/solver_settings.hpp"
#include "needle_sim/solver/stiffness_factor.hpp"
#include "needle_sim/solver/system_solver.hpp"
#include "needle_sim/tissue/compliance_cache.hpp"
#include "needle_sim/tissue/load_control.hpp"
#include "needle_sim/tissue/tissue_parameters.hpp"

namespace needle_sim {

class TissueBody {
 public:
  // Throws InputError (naming the scene key) when a Dirichlet or traction region selects
  // nothing, and std::invalid_argument for a degenerate mesh.
  // node_hanging (adaptive meshes): per node, its masters (node, weight); empty for a node
  // that is not hanging.
  // source: where the parameters came from (a scene file), for the messages.
  TissueBody(HexMesh mesh, const TissueParameters& tissue, const SolverSettings& solver, const std::string& source = "",
             const std::vector<std::vector<std::pair<int, double>>>& node_hanging = {});

  // A deep copy (mesh, rotations, state, loads, support, factor): stepping it gives what
  // stepping the original would (a prediction runs on one).
  TissueBody(const TissueBody& other);
  TissueBody& operator=(const TissueBody&) = delete;

  const HexMesh& mesh() const { return *mesh_; }
  const CorotationalHexModel& model() const { return *model_; }
  // Young's modulus adopted during a run, as a factor on the scene's (CorotationalHexModel::
  // setStiffnessScale): the factor in use becomes stale, and is refreshed as after rotations.
  void setStiffnessScale(double k) { model_->setStiffnessScale(k); }
  const DofMap& dofs() const { return dofs_; }
  const VecX& positions() const { return x_; }
  const VecX& velocities() const { return v_; }
  VecX displacements() const { return x_ - rest_; }
  const VecX& externalForce() const { return f_ext_; }
  const VecX& lumpedMass() const { return mass_; }  // per DOF (3n)

  // One dynamic step = freeMotion + (constraint corrections) + commit.
  StepStats stepDynamic(double h);
  // Solves the implicit Euler system without constraints; the velocity change is kept
  // (freeVelocityChange) and nothing moves until commit().
  StepStats freeMotion(double h);
  // Velocity change over the free DOFs (after freeMotion, plus corrections).
  const VecX& velocityChangeFree() const { return dv_free_; }
  void addVelocityChangeFree(const VecX& d) { dv_free_ += d; }
  // Applies the velocity change: v += dv, x += h v.
  void commit(double h);
  // Compliance of the given free DOFs from the body's factorisation: C = [A^-1]_{S,S}, from
  // cached columns of A^-1 (ComplianceCache). Columns of slightly different factors make C
  // slightly unsymmetric: it is symmetrised.
  void complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C) const;
  // dv_free += A^-1 E_S c, with the same (cached) columns: the constraint correction.
  void addInverseColumns(const std::vector<int>& free_dofs, const VecX& c);
  // Newton to equilibrium (static_newton.cpp); throws NumericalError when it does not converge.
  StepStats solveStatic();
  // An extra conservative force field for a static solve: adds its force at x to f (3n)
  // and its stiffness (-df/dx) as element blocks (replacing what K holds).
  using ExtraForce = std::function<void(const VecX& x, VecX& f, ElementBlocks& K)>;
  // Newton with displacement control (load_control.hpp): the load scale is an unknown too.
  using LoadControl = needle_sim::LoadControl;
  // limit (optional): the fraction a in (0, 1] of a Newton step (x + a dx, and the load
  // scale + a ds under control) that the extra terms allow (skull contact: how far vertices
  // that are off may press in at once).
  using StepLimit = std::function<double(const VecX& x, const VecX& dx)>;
  StepStats solveStatic(const ExtraForce& extra, double tolerance, int max_iterations,
                        LoadControl* control = nullptr, const StepLimit& limit = {});
  // Static solves that follow each other on nearly the same tangent (the brain shift's load
  // steps and multiplier updates) keep their factor from one call to the next while on; the
  // next call refactorises only when its extra blocks moved away from those in the factor
  // (doc/method.md "Static solves"). Turning it off drops the factor (it holds the extra
  // blocks, which later steps do not have).
  void keepStaticFactor(bool on);

  // Factors of the stiffness for the dual problems of goal-oriented estimates, K Z = G at the
  // positions' rotations with the support springs (support()) and the Dirichlet conditions
  // (StiffnessFactor): the stepping thread's, and one lent to a goal-oriented pass off it
  // (GoalPass). Made on first use, on the stepping thread; they live as long as this body.
  StiffnessFactor& dualFactor() const;
  StiffnessFactor& backgroundStiffnessFactor() const;

  double kineticEnergy() const;
  double elasticEnergy() const { return model_->elasticEnergy(x_); }
  // Work potential of the constant external loads, -f_ext . u.
  double loadPotential() const { return -f_ext_.dot(x_ - rest_); }

  // Sets positions/velocities (tests, restarts); prescribed DOFs are kept.
  // A fresh body made ready off the stepping thread (a deferred mesh change,
  // AdaptiveTissue::prepare): the factor of the dynamic step of size h at the current state,
  // and the compliance columns of the free DOFs of `elements` (where the constraint points
  // are), so that its first steps need neither.
  void prepareForSteps(double h, const std::vector<int>& elements);
  // The elements whose compliance columns the constraint solve will want soon (the next
  // constraint points': NeedleTissueInteraction::elementsAhead): a background factor refresh
  // computes their columns too, and the cache keeps them, so that a new shaft point or a tip
  // entering an element does not solve for them on the stepping thread. Not copied.
  void setElementsAhead(std::function<std::vector<int>()> elements) { elements_ahead_ = std::move(elements); }
  // Compliance columns solved where they were first wanted (the step's constraint solve, or
  // prepareForSteps), for DOFs without one: the solves the columns ahead are to spare.
  long complianceColumnsSolved() const { return columns_.solvedNew(); }
  // No background factor refresh while on (SystemSolver::holdRefresh): this body is about to
  // be replaced by one being built.
  void holdFactorRefresh(bool on) { solver_->holdRefresh(on); }
  bool factorRefreshRunning() const { return solver_->refreshRunning(); }
  void setState(const VecX& x, const VecX& v);
  // Adds nodal forces (3n) to the constant external loads (e.g. a manufactured body force).
  void addExternalForce(const VecX& f) { f_ext_ += f; }
  // Back to the scene's own loads (gravity, body force, tractions).
  void resetExternalForce() { f_ext_ = scene_f_ext_; }
  // Moves the prescribed DOFs to the values in x (other entries ignored).
  void setPrescribedPositions(const VecX& x);
  // Constant linear springs, force -K_s x with K_s given as symmetric positive semi-definite
  // element blocks (their anchors go in as external force): e.g. the skull holding the
  // shifted brain where it touched it. Part of the stiffness in every later solve.
  void setSupport(ElementBlocks blocks);
  const ElementBlocks& support() const { return support_; }

 private:
  void accumulate(StepStats& s, const LinearSolveStats& l) const;
  // After a background refresh was swapped in: the compliance columns it computed.
  void adoptRefreshColumns();
  // f -= c K_s y (the support springs).
  void addSupportProduct(const VecX& y, double c, VecX& f) const;
  const ElementBlocks* supportOrNull() const { return support_.element.empty() ? nullptr : &support_; }

  std::unique_ptr<HexMesh> mesh_;
  std::unique_ptr<CorotationalHexModel> model_;
  SolverSettings settings_;
  DofMap dofs_;
  std::unique_ptr<SystemSolver> solver_;
  std::vector<Mat3> rotations_now_;  // lagged rotations: those of the positions (a refresh's)
  VecX rest_, x_, v_, f_ext_, mass_, mass_free_;
  VecX scene_f_ext_;
  VecX dv_free_;     // this step's increment (free motion, then the constraint correction)
  VecX free_guess_, free_guess2_;  // the last two free motions: CG's initial guess for the next
  double step_h_ = 0;              // the time step the factor and the columns are for (0: none yet)
  ElementBlocks support_;
  // keepStaticFactor: whether on, and the extra blocks in the factor the last static solve
  // left (nullopt: none kept).
  bool keep_static_factor_ = false;
  std::optional<ElementBlocks> static_factor_blocks_;
  mutable ComplianceCache columns_;
  std::function<std::vector<int>()> elements_ahead_;
  // The free DOFs of `elements` (hanging ones: their masters'), each once.
  std::vector<int> freeDofsOf(const std::vector<int>& elements) const;
  // What a background refresh computes columns for: the cached ones and those ahead.
  std::vector<int> refreshColumnDofs();
  mutable std::unique_ptr<StiffnessFactor> dual_factor_, background_dual_factor_;  // made on first use
};

}  // namespace needle_sim
