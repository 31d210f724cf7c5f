#pragma once
// The in-memory form of a scene file (SI units throughout). The loader
// (scene_loader.hpp) fills it and guarantees every value is valid, so the rest of the
// library can rely on it.
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_sim/adapt/adaptivity_settings.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/contact/interaction_settings.hpp"
#include "needle_sim/fem/material.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"
#include "needle_sim/solver/system_solver.hpp"

namespace needle_sim {

struct BoxRegion {
  Vec3 min = Vec3::Zero();
  Vec3 max = Vec3::Zero();
};

// A region selecting grid nodes (Dirichlet conditions, tractions): a box, a sphere, or the
// nodes within `distance` of a surface patch (the triangles of a surface whose centroids
// lie in `patch`, or all of them), as for the brainstem and optic-nerve clamps.
struct Region {
  enum class Kind { Box, Sphere, SurfaceDistance } kind = Kind::Box;
  BoxRegion box;
  Vec3 center = Vec3::Zero();
  double radius = 0;
  std::shared_ptr<const TriangleMesh> surface;  // Kind::SurfaceDistance
  std::vector<int> patch;                       // its triangles that count
  double distance = 0;
  Vec3 patch_min = Vec3::Zero(), patch_max = Vec3::Zero();  // bounds of the patch

  bool contains(const Vec3& p, double tol) const {
    switch (kind) {
      case Kind::Box:
        return ((p - box.min).array() >= -tol).all() && ((p - box.max).array() <= tol).all();
      case Kind::Sphere:
        return (p - center).norm() <= radius + tol;
      case Kind::SurfaceDistance:
        if (((p - patch_min).array() < -(distance + tol)).any() || ((p - patch_max).array() > distance + tol).any())
          return false;
        return surface->distance(p, patch) <= distance + tol;
    }
    return false;
  }
};

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

struct TissueGeometry {
  enum class Kind { Box, Block, Surface } kind = Kind::Box;
  BoxRegion box;                 // Kind::Box
  std::array<Vec3, 8> corners{};  // Kind::Block, VTK hexahedron order
  // Kind::Surface: a closed surface (file, loaded and transformed to metres) with a grid
  // laid over it (immersed geometry).
  std::string surface_file;
  SurfaceTransform transform;
  std::shared_ptr<const TriangleMesh> surface;
  ImmersedGridSettings grid;
};

struct TissueScene {
  TissueGeometry geometry;
  Vec3i cells = Vec3i(1, 1, 1);
  LinearElasticMaterial material;
  Vec3 gravity = Vec3::Zero();     // m/s^2
  Vec3 body_force = Vec3::Zero();  // N/m^3
  std::vector<DirichletCondition> dirichlet;
  std::vector<TractionLoad> tractions;
};

struct SolverScene {
  enum class Mode { Dynamic, Static } mode = Mode::Dynamic;
  double rayleigh_mass = 0.0;       // alpha in C = alpha M + beta K
  double rayleigh_stiffness = 0.0;  // beta
  double static_tolerance = 1e-8;   // relative residual of the Newton iteration
  int static_max_iterations = 50;
  LinearSolverSettings linear;
};

struct NeedleMotionKey {
  double t = 0;
  Vec3 position = Vec3::Zero();
  Vec3 direction = Vec3::UnitX();
  double roll = 0;
};

// A needle (or cannula, electrode): a corotational beam whose base follows `motion`.
struct NeedleScene {
  std::string name = "needle";
  std::string key = "needle";  // where it came from in the file, for messages
  double length = 0.1;
  double radius = 1e-3;
  double inner_radius = 0.0;
  double young = 2e11, poisson = 0.3, density = 8000;
  int elements = 20;
  Vec3 base_position = Vec3::Zero();
  Vec3 base_direction = Vec3::UnitX();
  double base_roll = 0;
  std::vector<NeedleMotionKey> motion;  // strictly increasing t
  Vec3 tip_force = Vec3::Zero();        // external load at the tip [N], e.g. for verification
  Vec3 tip_moment = Vec3::Zero();       // [N m]
  Vec3 gravity = Vec3::Zero();          // [m/s^2]
};

struct ProbeScene {
  std::string name;
  Vec3 point = Vec3::Zero();
};

// A tracked anatomical target: a point, or the centroid of a closed surface (e.g. the STN).
struct TargetScene {
  std::string name;
  std::string key;
  Vec3 point = Vec3::Zero();
  std::shared_ptr<const TriangleMesh> surface;  // when given as a surface
};

// Quasi-static brain shift before the insertion (loss of CSF buoyancy): gravity acts on the
// tissue above the CSF level (or all of it), clamps hold, and the brain stays inside the
// skull: unilateral contact of the organ surface against the undeformed surface offset
// outwards by `gap`, or against a rigid skull surface.
struct BrainShiftScene {
  Vec3 gravity = Vec3(0, 0, -9.81);
  bool all = true;                      // the load acts on all of the tissue
  Vec3 csf_point = Vec3::Zero();        // else above the plane through this point, normal to gravity
  std::optional<double> density;        // default: the tissue's
  double gap = 0.0;                     // skull offset from the undeformed surface [m]
  std::shared_ptr<const TriangleMesh> skull;  // or a rigid skull surface
  bool skull_contact = true;
  bool skull_support = true;            // the skull keeps holding the brain during the insertion
  std::optional<double> target_shift;   // scale the load so that `target` moves this far [m]
  std::string target;                   // default: the first target
  int load_steps = 4;
  double tolerance = 1e-6;              // relative Newton residual per load step
};

struct Scene {
  std::string file;  // where it was loaded from ("" for scenes built in code)
  std::string name;
  std::string description;
  double dt = 0.01;
  double duration = 1.0;
  SolverScene solver;
  bool has_tissue = true;
  TissueScene tissue;
  std::vector<NeedleScene> needles;
  std::optional<InteractionSettings> interaction;
  std::optional<AdaptivitySettings> adaptivity;
  std::vector<ProbeScene> probes;
  std::vector<TargetScene> targets;
  std::optional<BrainShiftScene> brain_shift;

  long numSteps() const;
};

}  // namespace needle_sim
