#pragma once
#include "needle_sim/contact/constraint_solve.hpp"
#include "needle_sim/core/parameters.hpp"
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

  // The `interaction` section's keys (core/parameters.hpp); lateral_stiffness ('auto',
  // 'rigid' or a number) is read by the scene loader.
  static const Parameters<InteractionSettings>& parameters() {
    using S = InteractionSettings;
    static const Parameters<S> p =
        Parameters<S>()
            .real("puncture_force", [](S& s) -> double& { return s.puncture_force; }, "N", Range::nonNegative(),
                  "normal force at which the tip punctures the surface (λ_p0)", true)
            .real("cutting_force", [](S& s) -> double& { return s.cutting_force; }, "N", Range::nonNegative(),
                  "axial force the tip needs to cut, beyond friction (λ_c0)", true)
            .real("friction", [](S& s) -> double& { return s.friction; }, "", Range::nonNegative(),
                  "Coulomb coefficient μ (surface, tip and shaft)", true)
            .real("shaft_spacing", [](S& s) -> double& { return s.shaft_spacing; }, "m", Range::positive(),
                  "a shaft point every this much of cut path", true)
            .real("grip_pressure", [](S& s) -> double& { return s.grip_pressure; }, "Pa", Range::nonNegative(),
                  "radial pressure of the tissue on the needle wall: each shaft point's friction bound gains μ·2πr·p·`shaft_spacing`, so a straight insertion meets μ·2πr·p of friction per metre inserted; 0 keeps the paper's law ([method.md](method.md#needle-tissue-constraints))")
            .choice("solver.method", [](S& s) -> ConstraintSolver& { return s.solver; }, {"block", "gauss_seidel"},
                    "the constraint solve: block active set (exact on the axial rows; converges in soft tissue) or the paper's projected Gauss–Seidel ([method.md](method.md#constraint-solve))")
            .real("solver.tolerance", [](S& s) -> double& { return s.tolerance; }, "", Range::positive(),
                  "largest relative change of the multipliers in an iteration")
            .integer("solver.max_iterations", [](S& s) -> int& { return s.max_iterations; }, Range::closed(1, 1000000),
                     "outer iterations (block) or sweeps (Gauss–Seidel) per step; a step that reaches it is counted as unconverged");
    return p;
  }
};


}  // namespace needle_sim
