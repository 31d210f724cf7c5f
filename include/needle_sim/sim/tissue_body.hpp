#pragma once
// The deformable tissue as a body of the simulation: mesh, corotational model, boundary
// conditions, loads, state (x, v) and its linear solver.
//
// Dynamic step (linearised implicit Euler, Baraff & Witkin 1998), with K = -df/dx and
// Rayleigh damping C = alpha M + beta K:
//   (M + h C + h^2 K) dv = h ( f(x) + f_ext - h K v - C v ),   v += dv,   x += h v.
// Static solve: Newton on the corotational forces, K(x) dx = f(x) + f_ext, to equilibrium.
// Prescribed DOFs keep their position and zero velocity; they are not unknowns.
#include <algorithm>
#include <functional>
#include <memory>
#include <unordered_map>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/solver/dof_map.hpp"
#include "needle_sim/solver/system_solver.hpp"

namespace needle_sim {

struct StepStats {
  double forces_ms = 0;    // rotations, internal forces, right-hand side
  double assemble_ms = 0;  // sparse matrix assembly (only when refactorising)
  double factor_ms = 0;    // numeric factorisation
  double solve_ms = 0;     // CG iterations (or the direct solve)
  int linear_iterations = 0;
  int factorizations = 0;
  double linear_residual = 0;
  int newton_iterations = 0;     // static mode
  double newton_residual = 0;    // static mode, relative
  int constraint_points = 0;     // needle-tissue constraint points in the solve
  int constraint_iterations = 0; // projected Gauss-Seidel sweeps
  double constraint_residual = 0;
  double constraint_ms = 0;      // whole constraint phase (detection, compliance, PGS, correction)
  // Adaptivity (on the steps it runs): SPR estimate, marking + refinement/coarsening,
  // rebuilding the tissue body (state transfer, re-embedding, new factorisation).
  bool adapted = false;          // the estimate ran this step
  bool mesh_changed = false;
  int refined = 0, coarsened = 0;
  double estimate_ms = 0, mark_refine_ms = 0, rebuild_ms = 0;
  double adapt_ms() const { return estimate_ms + mark_refine_ms + rebuild_ms; }
  // Adds another phase's or step's costs: times and counts summed, residuals maxed.
  void accumulate(const StepStats& s) {
    forces_ms += s.forces_ms;
    assemble_ms += s.assemble_ms;
    factor_ms += s.factor_ms;
    solve_ms += s.solve_ms;
    linear_iterations += s.linear_iterations;
    factorizations += s.factorizations;
    linear_residual = std::max(linear_residual, s.linear_residual);
    newton_iterations += s.newton_iterations;
    newton_residual = std::max(newton_residual, s.newton_residual);
    constraint_points = std::max(constraint_points, s.constraint_points);
    constraint_iterations += s.constraint_iterations;
    constraint_residual = std::max(constraint_residual, s.constraint_residual);
    constraint_ms += s.constraint_ms;
    refined += s.refined;
    coarsened += s.coarsened;
    estimate_ms += s.estimate_ms;
    mark_refine_ms += s.mark_refine_ms;
    rebuild_ms += s.rebuild_ms;
  }
  double total_ms() const { return forces_ms + assemble_ms + factor_ms + solve_ms + constraint_ms + adapt_ms(); }
};

class TissueBody {
 public:
  // Throws InputError (naming the scene key) when a Dirichlet or traction region selects
  // nothing, and std::invalid_argument for a degenerate mesh.
  // node_hanging (adaptive meshes): per node, its masters (node, weight); empty for a node
  // that is not hanging.
  TissueBody(HexMesh mesh, const TissueScene& tissue, const SolverScene& solver, const std::string& file = "",
             const std::vector<std::vector<std::pair<int, double>>>& node_hanging = {});

  // A deep copy (mesh, rotations, state, loads, support, factor): stepping it gives what
  // stepping the original would (a prediction runs on one).
  TissueBody(const TissueBody& other);
  TissueBody& operator=(const TissueBody&) = delete;

  const HexMesh& mesh() const { return *mesh_; }
  const CorotationalHexModel& model() const { return *model_; }
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
  // Compliance of the given free DOFs from the body's factorisation: C = [A^-1]_{S,S}.
  // Columns of A^-1 are cached: a step solves only for DOFs it has not seen before, plus at
  // most kColumnRefresh columns computed with an older factor (the oldest first), so that a
  // refactorisation never costs hundreds of solves in one step. Columns of slightly
  // different factors make C slightly unsymmetric: it is symmetrised.
  void complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C) const;
  // dv_free += A^-1 E_S c, with the same (cached) columns: the constraint correction.
  void addInverseColumns(const std::vector<int>& free_dofs, const VecX& c);
  // Newton to equilibrium; throws NumericalError when it does not converge.
  StepStats solveStatic();
  // An extra conservative force field for a static solve: adds its force at x to f (3n)
  // and its stiffness (-df/dx) as element blocks (replacing what K holds).
  using ExtraForce = std::function<void(const VecX& x, VecX& f, ElementBlocks& K)>;
  // Displacement control: a load s * unit whose scale s is unknown besides x, fixed by one
  // scalar constraint c(x) = 0 (e.g. "the target has moved by 6.5 mm"). Each Newton step
  // solves the bordered system  K dx - ds unit = r,  grad c . dx = -c  with two solves by
  // one matrix, dx = K^-1 r + ds K^-1 unit, so the scale and the equilibrium converge
  // together instead of an equilibrium per trial scale.
  struct LoadControl {
    const VecX* unit = nullptr;                                    // load per unit scale (3n)
    std::function<double(const VecX& x, VecX& grad)> constraint;  // c(x) [m] and dc/dx (3n)
    double tolerance = 0;                                          // |c| to reach [m]
    double scale = 0;           // in: the scale of `unit` inside the external load; out: reached
    double max_scale = 1e3;     // beyond it the constraint is out of reach (NumericalError)
    double max_growth = 4;      // one step changes the scale by at most this factor (either way)
  };
  StepStats solveStatic(const ExtraForce& extra, double tolerance, int max_iterations,
                        LoadControl* control = nullptr);

  double kineticEnergy() const;
  double elasticEnergy() const { return model_->elasticEnergy(x_); }
  // Work potential of the constant external loads, -f_ext . u.
  double loadPotential() const { return -f_ext_.dot(x_ - rest_); }

  // Sets positions/velocities (tests, restarts); prescribed DOFs are kept.
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
  // f -= c K_s y (the support springs).
  void addSupportProduct(const VecX& y, double c, VecX& f) const;
  const ElementBlocks* supportOrNull() const { return support_.element.empty() ? nullptr : &support_; }

  std::unique_ptr<HexMesh> mesh_;
  std::unique_ptr<CorotationalHexModel> model_;
  SolverScene settings_;
  DofMap dofs_;
  std::unique_ptr<SystemSolver> solver_;
  VecX rest_, x_, v_, f_ext_, mass_, mass_free_;
  VecX scene_f_ext_;
  VecX dv_free_;  // last increment: warm start for CG
  ElementBlocks support_;
  const VecX& column(int free_dof) const;
  void cacheColumns(const std::vector<int>& free_dofs) const;
  struct CachedColumn {
    VecX x;
    long version;  // factorisation it came from
  };
  static constexpr int kColumnRefresh = 8;
  mutable std::unordered_map<int, CachedColumn> columns_;
};

}  // namespace needle_sim
