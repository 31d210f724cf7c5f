#pragma once
// Fixtures shared by the unit tests: the source tree's files, the unit cube with all faces
// clamped, and static solver settings.
#include <string>

#include "needle_sim/scene/scene.hpp"
#include "needle_sim/solver/solver_settings.hpp"
#include "needle_sim/tissue/tissue_parameters.hpp"

namespace needle_sim_test {

using namespace needle_sim;

// A path in the source tree (scenes, meshes, bad inputs).
inline std::string sourcePath(const std::string& rel) { return std::string(NEEDLE_SIM_SOURCE_DIR) + "/" + rel; }
inline std::string sceneFile(const std::string& name) { return sourcePath("config/scenes/" + name); }

// The unit cube [0, 1]^3 of the given material with all six faces held (their values are
// replaced where a test prescribes a field).
inline TissueParameters clampedUnitCube(double young, double poisson, double density = 1.0) {
  TissueParameters t;
  t.material = {young, poisson, density};
  for (int d = 0; d < 3; ++d)
    for (double side : {0.0, 1.0}) {
      DirichletCondition dc;
      dc.region.box.min = Vec3::Constant(-0.01);
      dc.region.box.max = Vec3::Constant(1.01);
      dc.region.box.min[d] = side - 0.01;
      dc.region.box.max[d] = side + 0.01;
      t.dirichlet.push_back(dc);
    }
  return t;
}

// Static Newton to the given tolerance with the direct solver.
inline SolverSettings staticDirect(double tolerance, int max_iterations = 50) {
  SolverSettings s;
  s.mode = SolverSettings::Mode::Static;
  s.static_tolerance = tolerance;
  s.static_max_iterations = max_iterations;
  s.linear.method = LinearSolverSettings::Method::Direct;
  return s;
}

}  // namespace needle_sim_test
