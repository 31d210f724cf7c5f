#pragma once
// Probes and targets: material points named by their planning (rest) positions, embedded in
// the tissue mesh in use (again after every mesh change, by those rest positions) and
// followed as the tissue moves. A target comes from the scene (targets[i]: a point or a
// closed surface's centroid, with its own regularisation radius) or is added at run time
// (setTarget: the node's ~set_target, the tool's --target).
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/scene/scene.hpp"

namespace needle_sim {

class TrackedPoints {
 public:
  struct Target {
    std::string name;
    Vec3 planned = Vec3::Zero();  // the planning (rest) position
    EmbeddedPoint point;          // in the mesh in use
    int scene_index = -1;         // its entry in the scene's targets; -1: added at run time
    std::shared_ptr<const TriangleMesh> surface;  // a target given as a surface (its centroid)
  };
  // immersed: the immersed grid (its inside test bounds the tissue) or nullptr.
  TrackedPoints(const Scene& scene, std::shared_ptr<const ImmersedGrid> immersed);

  // Embeds every probe and target in the locator's mesh. Throws InputError naming the scene
  // key of a point that lies outside the tissue.
  void embed(const PointLocator& locator);
  // The material point at rest position p; throws InputError(file, key) naming `what` when
  // it lies outside the tissue (or the organ surface).
  EmbeddedPoint embedPoint(const PointLocator& locator, const Vec3& p, const std::string& file,
                           const std::string& key, const std::string& what) const;

  int numProbes() const { return static_cast<int>(probes_.size()); }
  const std::string& probeName(int i) const { return probe_names_[i]; }
  const EmbeddedPoint& probe(int i) const { return probes_[i]; }

  int numTargets() const { return static_cast<int>(targets_.size()); }
  const Target& target(int i) const { return targets_[i]; }
  int findTarget(const std::string& name) const;
  // Adds a target at a planning position, or moves the one of this name there, embedded in
  // `mesh`; returns its index. Throws InputError (key "set_target...") for an empty name, a
  // non-finite point or one outside the tissue, and changes nothing then.
  int setTarget(const std::string& name, const Vec3& point, const HexMesh& mesh);
  // The regularisation radius of target i's goal-oriented estimate [m]: the scene's, or
  // `fallback` (negative in the scene, or added at run time).
  double radius(int i, double fallback) const;

 private:
  std::string file_;  // the scene file, for error messages
  std::vector<ProbeScene> probe_scene_;
  std::vector<TargetScene> target_scene_;
  std::vector<std::string> probe_names_;
  std::shared_ptr<const ImmersedGrid> immersed_;
  std::vector<EmbeddedPoint> probes_;
  std::vector<Target> targets_;
};

}  // namespace needle_sim
