#pragma once
// Parameters of the needle-tissue interaction (scene section `interaction`).

namespace needle_sim {

struct InteractionSettings {
  double puncture_force = 1.0;  // [N]
  double cutting_force = 0.5;   // [N]
  double friction = 0.1;        // Coulomb coefficient
  double shaft_spacing = 1e-3;  // [m]
  double tolerance = 1e-8;      // PGS: relative change of the multipliers
  int max_iterations = 200;
};


}  // namespace needle_sim
