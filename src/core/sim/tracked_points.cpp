#include "needle_sim/sim/tracked_points.hpp"

#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

TrackedPoints::TrackedPoints(const Scene& scene, std::shared_ptr<const ImmersedGrid> immersed)
    : file_(scene.file), probe_scene_(scene.probes), target_scene_(scene.targets), immersed_(std::move(immersed)) {
  for (const auto& p : scene.probes) probe_names_.push_back(p.name);
  for (size_t i = 0; i < scene.targets.size(); ++i) {
    const TargetScene& t = scene.targets[i];
    targets_.push_back({t.name, t.point, EmbeddedPoint{}, static_cast<int>(i), t.surface});
  }
}

EmbeddedPoint TrackedPoints::embedPoint(const PointLocator& locator, const Vec3& p, const std::string& file,
                                        const std::string& key, const std::string& what) const {
  EmbeddedPoint ep;
  const bool outside = immersed_ && !immersed_->insideTest().inside(p);
  if (outside || !locator.locate(p, ep)) {
    std::ostringstream m;
    m << what << " (" << p.transpose() << ") lies outside the tissue" << (immersed_ ? " surface" : "");
    throw InputError(file, key, m.str());
  }
  return ep;
}

void TrackedPoints::embed(const PointLocator& locator) {
  probes_.clear();
  for (size_t i = 0; i < probe_scene_.size(); ++i)
    probes_.push_back(embedPoint(locator, probe_scene_[i].point, file_, "probes[" + std::to_string(i) + "].point", "point"));
  for (auto& t : targets_) {
    const bool from_scene = t.scene_index >= 0;
    const std::string key = from_scene ? target_scene_[t.scene_index].key + (t.surface ? ".surface" : ".point")
                                       : "set_target.point";
    t.point = embedPoint(locator, t.planned, from_scene ? file_ : "", key,
                         t.surface ? "the surface's centroid" : "point");
  }
}

int TrackedPoints::findTarget(const std::string& name) const {
  for (int i = 0; i < numTargets(); ++i)
    if (targets_[i].name == name) return i;
  return -1;
}

int TrackedPoints::setTarget(const std::string& name, const Vec3& point, const HexMesh& mesh) {
  if (name.empty()) throw InputError("", "set_target.name", "must not be empty");
  if (!point.allFinite()) throw InputError("", "set_target.point", "must be finite");
  const EmbeddedPoint ep = embedPoint(PointLocator(mesh), point, "", "set_target.point", "point");
  int i = findTarget(name);
  if (i < 0) {
    i = numTargets();
    targets_.push_back({name, point, ep, -1, nullptr});
  } else {
    targets_[i] = {name, point, ep, -1, nullptr};
  }
  return i;
}

double TrackedPoints::radius(int i, double fallback) const {
  const int s = targets_[i].scene_index;
  const double r = s >= 0 ? target_scene_[s].radius : -1;
  return r >= 0 ? r : fallback;
}

}  // namespace needle_sim
