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
  // The needle-tissue interface's lateral stiffness per unit path length [Pa] (doc/method.md,
  // "Interface compliance"): 0, rigid ties (the paper); > 0, this value; Auto, the elastic
  // near field around the needle that the mesh does not resolve, from the tissue's moduli,
  // the needle's radius and the element size. A bevel needle's scene defaults to Auto.
  enum class LateralStiffness { Rigid, Value, Auto };
  LateralStiffness lateral_mode = LateralStiffness::Rigid;
  double lateral_stiffness = 0.0;
  ConstraintSolver solver = ConstraintSolver::BlockActiveSet;
  double tolerance = 1e-8;      // relative change of the multipliers in an iteration
  int max_iterations = 200;
};


}  // namespace needle_sim
