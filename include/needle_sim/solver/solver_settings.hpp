#pragma once
// How the bodies are advanced and solved (the scene's `solver` section): dynamic (one
// linearised implicit Euler step per time step) or static (Newton to equilibrium), Rayleigh
// damping, the static tolerance, the linear solver.
#include "needle_sim/core/parameters.hpp"
#include "needle_sim/solver/system_solver.hpp"

namespace needle_sim {

struct SolverSettings {
  enum class Mode { Dynamic, Static } mode = Mode::Dynamic;
  double rayleigh_mass = 0.0;       // alpha in C = alpha M + beta K
  double rayleigh_stiffness = 0.0;  // beta
  double static_tolerance = 1e-8;   // relative residual of the Newton iteration
  int static_max_iterations = 50;
  // Static Newton with the corotational tangent's rotation part (GMRES; doc/method.md
  // "Static solves"): quadratic convergence under large rotations, at a dearer linear solve.
  bool static_rotation_tangent = false;
  LinearSolverSettings linear;

  // The `solver` section's keys (core/parameters.hpp).
  static const Parameters<SolverSettings>& parameters() {
    static const Parameters<SolverSettings> p =
        Parameters<SolverSettings>()
            .choice("mode", [](SolverSettings& s) -> Mode& { return s.mode; }, {"dynamic", "static"},
                    "dynamic: one linearised implicit Euler step per time step; static: Newton to equilibrium per step ([method.md](method.md#static-solves))")
            .real("rayleigh.mass", [](SolverSettings& s) -> double& { return s.rayleigh_mass; }, "1/s",
                  Range::nonNegative(), "α in the damping C = αM + βK")
            .real("rayleigh.stiffness", [](SolverSettings& s) -> double& { return s.rayleigh_stiffness; }, "s",
                  Range::nonNegative(), "β in the damping C = αM + βK")
            .real("static.tolerance", [](SolverSettings& s) -> double& { return s.static_tolerance; }, "",
                  Range::positive(), "relative residual (or relative Newton correction) at which a static solve stops")
            .integer("static.max_iterations", [](SolverSettings& s) -> int& { return s.static_max_iterations; },
                     Range::closed(1, 100000), "Newton iterations before a numerical failure")
            .flag("static.rotation_tangent", [](SolverSettings& s) -> bool& { return s.static_rotation_tangent; },
                  "Newton with the corotational tangent's rotation part (GMRES on each step): quadratic convergence under large rotations, dearer linear solves; needs `linear.method: pcg` ([method.md](method.md#static-solves))")
            .choice("linear.method", [](SolverSettings& s) -> LinearSolverSettings::Method& { return s.linear.method; },
                    {"direct", "pcg"}, "direct: refactorise every solve; pcg: CG on the exact matrix, preconditioned by an earlier factorisation ([method.md](method.md#time-integration))")
            .real("linear.tolerance", [](SolverSettings& s) -> double& { return s.linear.tolerance; }, "",
                  Range::open(0, 1), "CG relative residual")
            .integer("linear.max_iterations", [](SolverSettings& s) -> int& { return s.linear.max_iterations; },
                     Range::closed(1, 1000000), "CG iterations before the factor is refreshed and the solve repeated")
            .integer("linear.refresh_iterations", [](SolverSettings& s) -> int& { return s.linear.refresh_iterations; },
                     Range::closed(0, 1000000), "refactorise before the next solve when CG needed more than this")
            .integer("linear.refactor_every", [](SolverSettings& s) -> int& { return s.linear.refactor_every; },
                     Range::closed(0, 1000000), "also refactorise every N solves (0: only on demand)")
            .choice("linear.ordering", [](SolverSettings& s) -> Ordering& { return s.linear.ordering; },
                    {"auto", "amd", "metis"}, "CHOLMOD's fill-reducing ordering")
            .flag("linear.async", [](SolverSettings& s) -> bool& { return s.linear.async; },
                  "pcg: refresh the factor on a background thread while the steps go on with the old one ([method.md](method.md#time-integration)); false: on the stepping thread")
            .integer("linear.async_lag", [](SolverSettings& s) -> int& { return s.linear.async_lag; },
                     Range::closed(0, 1000000), "swap a background factor in this many solves after the request, waiting if it is late (deterministic); 0: as soon as it is ready (never waits; the results then vary with the threads' timing: negligibly on dbs_adaptive, by millimetres on dbs_coarse, whose shaft grip releases in a stick-slip ([benchmarks.md](benchmarks.md#deep-brain-stimulation), reproducibility))")
            .real("linear.rotation_drift", [](SolverSettings& s) -> double& { return s.linear.rotation_drift; }, "rad",
                  Range::closed(0, 0.5), "dynamic steps: the tissue's stiffness and forces take the element rotations of the factor in use, refreshed (in the background with `linear.async`) once an element's rotation has turned more than this from them; every solve is then the factor's own matrix (one CG iteration), where a nearly incompressible tissue's stale factor takes many. 0: the rotations of every step ([method.md](method.md#time-integration))")
            .flag("linear.columns_ahead", [](SolverSettings& s) -> bool& { return s.linear.columns_ahead; },
                  "dynamic steps with needles: a background factor refresh also computes the compliance columns of the elements the needles' next constraint points will lie in (the next shaft point, the tip ahead), so that the step meeting them does not solve for them; the live loop turns it on with lagged rotations ([method.md](method.md#constraint-solve))");
    return p;
  }
};

}  // namespace needle_sim
