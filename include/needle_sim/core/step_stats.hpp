#pragma once
// Where a step's time goes, and its solver counters: every body's step returns one, the
// simulation adds them up (StepStats::accumulate), the recorder, the benchmark and the node
// report them.
#include <algorithm>

namespace needle_sim {

struct StepStats {
  double forces_ms = 0;    // rotations, internal forces, right-hand side
  double assemble_ms = 0;  // sparse matrix assembly (only when refactorising)
  double factor_ms = 0;    // numeric factorisation
  double solve_ms = 0;     // CG iterations (or the direct solve)
  int linear_iterations = 0;
  int factorizations = 0;        // on the stepping thread
  int stale_fallbacks = 0;       // CG on a stale factor ran out of its budget (then refactorised)
  int async_factorizations = 0;  // background refreshes swapped in this step
  int factor_waits = 0;          // ... of which the step had to wait for
  double factor_wait_ms = 0;     // time waited (part of solve_ms)
  double linear_residual = 0;
  int newton_iterations = 0;     // static mode
  double newton_residual = 0;    // static mode, relative
  int constraint_points = 0;     // needle-tissue constraint points in the solve
  int constraint_iterations = 0; // projected Gauss-Seidel sweeps
  double constraint_residual = 0;
  bool constraint_converged = true;  // the constraint solve met its tolerance
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
    stale_fallbacks += s.stale_fallbacks;
    async_factorizations += s.async_factorizations;
    factor_waits += s.factor_waits;
    factor_wait_ms += s.factor_wait_ms;
    linear_residual = std::max(linear_residual, s.linear_residual);
    newton_iterations += s.newton_iterations;
    newton_residual = std::max(newton_residual, s.newton_residual);
    constraint_points = std::max(constraint_points, s.constraint_points);
    constraint_iterations += s.constraint_iterations;
    constraint_residual = std::max(constraint_residual, s.constraint_residual);
    constraint_converged = constraint_converged && s.constraint_converged;
    constraint_ms += s.constraint_ms;
    refined += s.refined;
    coarsened += s.coarsened;
    estimate_ms += s.estimate_ms;
    mark_refine_ms += s.mark_refine_ms;
    rebuild_ms += s.rebuild_ms;
  }
  double total_ms() const { return forces_ms + assemble_ms + factor_ms + solve_ms + constraint_ms + adapt_ms(); }
};

}  // namespace needle_sim
