#pragma once
// What the tissue body needs to know (the scene's `tissue` section without its geometry):
// material, body loads, boundary conditions by region.
#include <array>
#include <string>
#include <vector>

#include "needle_sim/core/parameters.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/material.hpp"
#include "needle_sim/geometry/region.hpp"

namespace needle_sim {

struct DirichletCondition {
  Region region;
  Vec3 displacement = Vec3::Zero();
  std::array<bool, 3> components{{true, true, true}};  // which of x, y, z are prescribed
};

// Uniform traction (Pa) on the boundary faces lying in a region.
struct TractionLoad {
  Region region;
  Vec3 traction = Vec3::Zero();
};

struct TissueParameters {
  LinearElasticMaterial material;
  Vec3 gravity = Vec3::Zero();     // m/s^2
  Vec3 body_force = Vec3::Zero();  // N/m^3
  std::vector<DirichletCondition> dirichlet;
  std::vector<TractionLoad> tractions;

  // The keys of the `tissue` section that are values (core/parameters.hpp); the geometry, the
  // grid and the lists of conditions and tractions are read by the scene loader.
  static const Parameters<TissueParameters>& parameters() {
    using S = TissueParameters;
    static const Parameters<S> p =
        Parameters<S>()
            .real("material.young", [](S& s) -> double& { return s.material.young; }, "Pa", Range::positive(),
                  "Young's modulus E", true)
            .real("material.poisson", [](S& s) -> double& { return s.material.poisson; }, "", Range::open(-1, 0.5),
                  "Poisson's ratio ν", true)
            .real("material.density", [](S& s) -> double& { return s.material.density; }, "kg/m^3", Range::positive(),
                  "ρ", true)
            .choice("element", [](S& s) -> HexFormulation& { return s.material.element; },
                    {"trilinear", "bbar", "incompatible_modes", "incompatible_modes_bbar"},
                    "how the hexahedra integrate the material: full 2x2x2 Gauss, the mean volume strain (B-bar), "
                    "nine condensed incompatible modes, or both (doc/method.md \"Tissue\")")
            .vector("gravity", [](S& s) -> Vec3& { return s.gravity; }, "m/s^2", "body load ρg")
            .vector("body_force", [](S& s) -> Vec3& { return s.body_force; }, "N/m^3", "body load per volume");
    return p;
  }
};

}  // namespace needle_sim
