#pragma once
#include "needle_sim/contact/constraint_solve.hpp"
// Parameters of the needle-tissue interaction (scene section `interaction`).

namespace needle_sim {

struct InteractionSettings {
  double puncture_force = 1.0;  // [N]
  double cutting_force = 0.5;   // [N]
  double friction = 0.1;        // Coulomb coefficient
  double shaft_spacing = 1e-3;  // [m]
  // The tissue's radial pressure on the needle wall [Pa] (doc/method.md, "Needle-tissue
  // constraints"): each shaft point's friction bound becomes
  // friction * (|lateral force| + 2 pi r grip_pressure shaft_spacing), r the needle's outer
  // radius there, so a straight insertion meets friction proportional to the inserted length.
  double grip_pressure = 0.0;
  ConstraintSolver solver = ConstraintSolver::BlockActiveSet;
  double tolerance = 1e-8;      // relative change of the multipliers in an iteration
  int max_iterations = 200;
};


}  // namespace needle_sim
