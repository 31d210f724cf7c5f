#include "needle_sim/sim/adaptive_tissue.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& t) {
  if (t.geometry.kind == TissueGeometry::Kind::Box)
    return HexMesh::box(t.geometry.box.min, t.geometry.box.max, t.cells);
  if (t.geometry.kind == TissueGeometry::Kind::Surface) return ImmersedGrid(t.geometry.surface, t.geometry.grid).mesh();
  return HexMesh::mappedBlock(t.geometry.corners, t.cells);
}

AdaptiveTissue::AdaptiveTissue(const Scene& scene) : scene_(&scene) {
  HexMesh mesh;
  const bool immersed = scene.tissue.geometry.kind == TissueGeometry::Kind::Surface;
  try {
    if (immersed) {
      immersed_ = std::make_shared<const ImmersedGrid>(scene.tissue.geometry.surface, scene.tissue.geometry.grid);
      mesh = immersed_->mesh();
      for (int e = 0; e < mesh.numElements(); ++e) cell_fraction_[e] = immersed_->fraction(e);
    } else {
      mesh = buildTissueMesh(scene.tissue);
    }
    if (scene.adaptivity) {
      // The tissue is numbered as the adaptive forest numbers its active mesh.
      adaptation_ = std::make_unique<MeshAdaptation>(*scene.adaptivity, mesh);
      // Round-off: the energy-norm error of a strain of 1e-12 over the body's box,
      // sqrt(E V) 1e-12 (an unloaded phantom refined ahead of its needle: 3e-16 of 4e-13).
      Vec3 lo = mesh.node(0), hi = mesh.node(0);
      for (int i = 1; i < mesh.numNodes(); ++i) lo = lo.cwiseMin(mesh.node(i)), hi = hi.cwiseMax(mesh.node(i));
      adaptation_->setRoundOff(1e-12 * std::sqrt(scene.tissue.material.young * (hi - lo).prod()));
      mesh = adaptation_->active().mesh;
      if (immersed) setFractions(*adaptation_, mesh, adaptation_->active().cell);
    }
    body_ = std::make_unique<TissueBody>(std::move(mesh), scene.tissue, scene.solver, scene.file);
    if (adaptation_) {
      levels_ = adaptation_->active().level;
      hanging_ = adaptation_->active().numHanging();
    }
  } catch (const std::invalid_argument& e) {
    throw InputError(scene.file, "tissue.geometry", std::string("invalid mesh: ") + e.what());
  } catch (const InputError& e) {  // a region of the tissue's parameters: its key in the scene
    throw InputError(scene.file, "tissue." + e.key(), e.problem());
  }
  if (immersed) organ_ = std::make_unique<EmbeddedSurface>(scene.tissue.geometry.surface, body_->mesh());
}

AdaptiveTissue::AdaptiveTissue(const AdaptiveTissue& o, const Scene& scene)
    : scene_(&scene),
      immersed_(o.immersed_),
      cell_fraction_(o.cell_fraction_),
      body_(std::make_unique<TissueBody>(*o.body_)),
      levels_(o.levels_),
      hanging_(o.hanging_),
      reference_(o.reference_),
      shifted_(o.shifted_),
      load_scale_(o.load_scale_),
      loads_with_stiffness_(o.loads_with_stiffness_),
      stiffness_scale_(o.stiffnessScale()) {
  if (o.organ_) organ_ = std::make_unique<EmbeddedSurface>(o.organ_->restPtr(), body_->mesh());
  if (o.adaptation_) adaptation_ = std::make_unique<MeshAdaptation>(*o.adaptation_);
}

MeshAdaptation* AdaptiveTissue::adaptation() {
  if (lent_) throw std::logic_error("AdaptiveTissue: the forest asked for while a background pass holds it");
  return adaptation_.get();
}

void AdaptiveTissue::setFractions(const MeshAdaptation& adaptation, HexMesh& mesh, const std::vector<int>& cells) {
  const RefinableHexMesh& forest = adaptation.forest();
  std::vector<double> f(mesh.numElements());
  for (int e = 0; e < mesh.numElements(); ++e) {
    auto it = cell_fraction_.find(cells[e]);
    if (it == cell_fraction_.end()) {
      const int parent = forest.parent(cells[e]);
      auto pit = parent >= 0 ? cell_fraction_.find(parent) : cell_fraction_.end();
      double frac;
      if (pit != cell_fraction_.end() && pit->second >= 1.0) {
        frac = 1.0;
      } else {
        const auto X = mesh.elementCorners(e);
        frac = immersed_->boxFraction(X.colwise().minCoeff().transpose(), X.colwise().maxCoeff().transpose());
      }
      it = cell_fraction_.emplace(cells[e], frac).first;
    }
    f[e] = std::max(it->second, immersed_->settings().min_fraction);
  }
  mesh.setFractions(std::move(f));
}

AdaptiveTissue::MeshChange AdaptiveTissue::forestMesh(MeshAdaptation& forest) {
  const auto& act = forest.active();
  MeshChange c;
  c.mesh = act.mesh;
  if (immersed_) setFractions(forest, c.mesh, act.cell);
  c.hanging = act.hanging;
  c.levels = act.level;
  c.num_hanging = act.numHanging();
  return c;
}

std::shared_ptr<AdaptiveTissue::Prepared> AdaptiveTissue::prepare(MeshChange c, const VecX& x, const VecX& v,
                                                                  bool persistent_loads, double steps_h,
                                                                  const std::vector<Vec3>& points) const {
  const Scene& scene = *scene_;
  auto p = std::make_shared<Prepared>();
  p->body = std::make_unique<TissueBody>(std::move(c.mesh), scene.tissue, scene.solver, scene.file, c.hanging);
  p->body->setState(x, v);
  p->stiffness_scale = stiffnessScale();
  if (p->stiffness_scale != 1.0) p->body->setStiffnessScale(p->stiffness_scale);
  const HexMesh& m = p->body->mesh();
  if (immersed_) p->organ = std::make_unique<EmbeddedSurface>(scene.tissue.geometry.surface, m);
  if (persistent_loads && shift_)
    shift_->applyPersistentLoads(*p->body, p->organ.get(), load_scale_, loads_with_stiffness_ ? p->stiffness_scale : 1.0);
  p->locator = std::make_unique<PointLocator>(m);
  if (steps_h > 0) {
    const PointLocator& locator = *p->locator;
    std::vector<int> elements;
    for (const Vec3& r : points) {
      EmbeddedPoint ep;
      if (locator.locate(r, ep) || locator.locateNearest(r, ep)) elements.push_back(ep.element);
    }
    std::sort(elements.begin(), elements.end());
    elements.erase(std::unique(elements.begin(), elements.end()), elements.end());
    p->body->prepareForSteps(steps_h, elements);
    p->spr = std::make_unique<SprEstimator>(p->body->model());
    if (scene.interaction) p->binding = TissueBinding::make(m, p->organ.get());
  }
  p->levels = std::move(c.levels);
  p->num_hanging = c.num_hanging;
  return p;
}

std::shared_ptr<AdaptiveTissue::Prepared> AdaptiveTissue::copyPrepared(const Prepared& p) {
  auto q = std::make_shared<Prepared>();
  q->body = std::make_unique<TissueBody>(*p.body);
  if (p.organ) q->organ = std::make_unique<EmbeddedSurface>(p.organ->restPtr(), q->body->mesh());
  q->levels = p.levels;
  q->num_hanging = p.num_hanging;
  q->stiffness_scale = p.stiffness_scale;
  // Its lookups are made at its own switch, on the thread that steps the copy (a
  // prediction's): a copy taken on the stepping thread for an estimate never gets there.
  return q;
}

void AdaptiveTissue::switchTo(Prepared& p, bool carry_velocities, bool retire) {
  // The state of now, carried over; the body keeps the factor and columns made for it.
  const VecX x = adaptation_->transfer(body_->positions());
  const VecX v = carry_velocities ? adaptation_->transfer(body_->velocities()) : VecX::Zero(x.size());
  if (reference_.size()) reference_ = adaptation_->transfer(reference_);
  if (shifted_.size()) shifted_ = adaptation_->transfer(shifted_);
  std::unique_ptr<TissueBody> old = std::move(body_);
  body_ = std::move(p.body);
  body_->setState(x, v);
  if (immersed_) organ_ = std::move(p.organ);
  if (!p.locator) p.locator = std::make_unique<PointLocator>(body_->mesh());
  levels_ = std::move(p.levels);
  hanging_ = p.num_hanging;
  // A stiffness adopted while the body was prepared in the background.
  const double k = stiffnessScale();
  if (p.stiffness_scale != k) {
    body_->setStiffnessScale(k);
    if (shift_ && loads_with_stiffness_)
      body_->addExternalForce((k - p.stiffness_scale) * shift_->shiftLoad(*body_, organ_.get(), load_scale_));
  }
  if (on_switch_) {
    Switch s{*body_, organ_.get(), *p.locator, p.binding.locator ? &p.binding : nullptr, std::move(p.spr)};
    on_switch_(s);
  }
  if (retire) retired_ = std::move(old);  // freed on the next pass's or build's thread
}

void AdaptiveTissue::setStiffnessScale(double k) {
  const double old = stiffnessScale();
  if (k == old) return;
  body_->setStiffnessScale(k);
  if (shift_ && loads_with_stiffness_) body_->addExternalForce((k - old) * shift_->shiftLoad(*body_, organ_.get(), load_scale_));
  stiffness_scale_.store(k, std::memory_order_relaxed);
}

void AdaptiveTissue::rebuild(bool persistent_loads) {
  MeshAdaptation& forest = *adaptation();
  const VecX x = forest.transfer(body_->positions());
  const VecX v = persistent_loads ? forest.transfer(body_->velocities()) : VecX::Zero(x.size());
  std::shared_ptr<Prepared> p = prepare(forestMesh(forest), x, v, persistent_loads);
  switchTo(*p, persistent_loads, false);
}

}  // namespace needle_sim
