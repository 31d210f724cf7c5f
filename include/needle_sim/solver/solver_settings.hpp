#pragma once
// How the bodies are advanced and solved (the scene's `solver` section): dynamic (one
// linearised implicit Euler step per time step) or static (Newton to equilibrium), Rayleigh
// damping, the static tolerance, the linear solver.
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
};

}  // namespace needle_sim
