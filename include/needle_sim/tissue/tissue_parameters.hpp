#pragma once
// What the tissue body needs to know (the scene's `tissue` section without its geometry):
// material, body loads, boundary conditions by region.
#include <array>
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/material.hpp"
#include "needle_sim/geometry/region.hpp"

namespace needle_sim {

struct DirichletCondition {
  Region region;
  Vec3 displacement = Vec3::Zero();
  std::array<bool, 3> components{{true, true, true}};  // which of x, y, z are prescribed
  std::string key;                                     // e.g. "tissue.dirichlet[0]", for messages
};

// Uniform traction (Pa) on the boundary faces lying in a region.
struct TractionLoad {
  Region region;
  Vec3 traction = Vec3::Zero();
  std::string key;
};

struct TissueParameters {
  LinearElasticMaterial material;
  Vec3 gravity = Vec3::Zero();     // m/s^2
  Vec3 body_force = Vec3::Zero();  // N/m^3
  std::vector<DirichletCondition> dirichlet;
  std::vector<TractionLoad> tractions;
};

}  // namespace needle_sim
