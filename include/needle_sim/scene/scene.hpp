#pragma once
// The in-memory form of a scene file (SI units throughout): the settings of each module
// (tissue, needles, solver, interaction, adaptivity, brain shift), plus what only the scene
// knows (geometry, probes, targets, time). The loader (scene_loader.hpp) fills it and
// guarantees every value is valid; a Simulation is built from it and never changes it (its
// own run-time state: time step, targets added at run time, lives in the Simulation).
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_sim/adapt/adaptivity_settings.hpp"
#include "needle_sim/brain/brain_shift_settings.hpp"
#include "needle_sim/contact/interaction_settings.hpp"
#include "needle_sim/core/parameters.hpp"
#include "needle_sim/core/types.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/geometry/region.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"
#include "needle_sim/needle/needle_parameters.hpp"
#include "needle_sim/solver/solver_settings.hpp"
#include "needle_sim/tissue/tissue_parameters.hpp"

namespace needle_sim {

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

// The scene's `tissue` section: the geometry the mesh is built from, and what the tissue
// body needs (TissueParameters).
struct TissueScene : TissueParameters {
  TissueGeometry geometry;
  Vec3i cells = Vec3i(1, 1, 1);
};

// A scene's needle entry: what the needle body needs, and where it came from in the file.
struct NeedleScene : NeedleParameters {
  std::string key = "needle";  // for messages
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
  // Radius of the ball the goal-oriented error estimate averages the displacement over
  // [m]; negative: half the finest element's edge.
  double radius = -1;
};

struct Scene {
  std::string file;  // where it was loaded from ("" for scenes built in code)
  std::string name;
  std::string description;
  double dt = 0.01;
  double duration = 1.0;
  SolverSettings solver;
  bool has_tissue = true;
  TissueScene tissue;
  std::vector<NeedleScene> needles;
  std::optional<InteractionSettings> interaction;
  std::optional<AdaptivitySettings> adaptivity;
  std::vector<ProbeScene> probes;
  std::vector<TargetScene> targets;
  std::optional<BrainShiftSettings> brain_shift;

  long numSteps() const;

  // The `time` section's keys (core/parameters.hpp).
  static const Parameters<Scene>& timeParameters() {
    static const Parameters<Scene> p =
        Parameters<Scene>()
            .real("dt", [](Scene& s) -> double& { return s.dt; }, "s", Range::positive(),
                  "time step (dynamic) or load step (static)", true)
            .real("duration", [](Scene& s) -> double& { return s.duration; }, "s", Range::positive(),
                  "simulated time, at most 1e9 steps; steps = ⌈duration/dt⌉", true);
    return p;
  }
};

}  // namespace needle_sim
