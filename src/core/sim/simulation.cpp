#include "needle_sim/sim/simulation.hpp"

#include <algorithm>
#include <atomic>
#include <thread>
#include <future>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <sstream>

#include "needle_sim/core/background_priority.hpp"
#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& t) {
  if (t.geometry.kind == TissueGeometry::Kind::Box)
    return HexMesh::box(t.geometry.box.min, t.geometry.box.max, t.cells);
  if (t.geometry.kind == TissueGeometry::Kind::Surface) return ImmersedGrid(t.geometry.surface, t.geometry.grid).mesh();
  return HexMesh::mappedBlock(t.geometry.corners, t.cells);
}

Simulation::Simulation(const Scene& scene, const Options& options) : scene_(scene), dt_(scene.dt), options_(options) {
  for (const auto& n : scene.needles) needles_.push_back(std::make_unique<NeedleBody>(n, scene.solver));
  if (!scene.has_tissue) return;
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
      every_steps_ = scene.adaptivity->every_steps;
      mesh = adaptation_->active().mesh;
      if (immersed) setFractions(mesh, adaptation_->active().cell);
    }
    tissue_ = std::make_unique<TissueBody>(std::move(mesh), scene.tissue, scene.solver, scene.file);
    noteActiveMesh();
  } catch (const std::invalid_argument& e) {
    throw InputError(scene.file, "tissue.geometry", std::string("invalid mesh: ") + e.what());
  }
  if (immersed) organ_ = std::make_unique<EmbeddedSurface>(scene.tissue.geometry.surface, tissue_->mesh());
  diag_ = (tissue_->mesh().boundsMax() - tissue_->mesh().boundsMin()).norm();
  embedProbes();
  for (const auto& t : scene.targets) targets_.push_back({t.name, t.point, EmbeddedPoint{}, t.key, t.surface});
  embedTargets();
  {
    // The regularised point of the goal estimate: a ball of half the finest element's edge.
    const auto X = tissue_->mesh().elementCorners(0);
    const double edge = (X.colwise().maxCoeff() - X.colwise().minCoeff()).minCoeff();
    qoi_radius_ = 0.5 * edge / std::pow(2.0, scene.adaptivity ? scene.adaptivity->max_level : 0);
  }
  if (scene.adaptivity && scene.adaptivity->estimator == AdaptivitySettings::Estimator::Goal) {
    options_.target_errors = true;
    for (const auto& name : scene.adaptivity->goal_targets) goal_targets_.push_back(findTarget(name));
  }
  PointLocator locator(tissue_->mesh());
  // A needle must start outside the tissue: puncture happens on the surface.
  for (size_t n = 0; n < needles_.size(); ++n)
    for (int i = 0; i < needles_[n]->beam().numNodes(); ++i) {
      EmbeddedPoint ep;
      const Vec3& p = needles_[n]->state().p[i];
      const bool inside = immersed ? immersed_->insideTest().inside(p) : locator.locate(p, ep);
      if (inside) {
        std::ostringstream m;
        m << "the needle starts inside the tissue (node " << i << " at (" << p.transpose()
          << ")); place its tip outside the tissue surface";
        throw InputError(scene.file, scene.needles[n].key + ".base.position", m.str());
      }
    }
  if (scene.interaction) {
    std::vector<NeedleBody*> nd;
    for (auto& n : needles_) nd.push_back(n.get());
    interaction_ = std::make_unique<NeedleTissueInteraction>(*scene.interaction, *tissue_, nd, organ_.get());
  }
  // The brain shift's static solves (and the first step's factor after them) may use more
  // BLAS threads. They pay off only for large factors: on the adaptive DBS mesh's first grid
  // (3,000 DOFs) two threads gained nothing and were sometimes slower (2026-12-04,
  // doc/benchmarks.md). A scene without the shift leaves the count alone.
  constexpr int kSetupThreadsMinDofs = 10000;
  ScopedBlasThreads setup_threads(scene.brain_shift && tissue_->mesh().numDofs() >= kSetupThreadsMinDofs ? setupThreads() : 0);
  if (scene.brain_shift) preStep();
  if (scene.brain_shift && scene.brain_shift->replan) replanNeedles();
  for (int i = 0; i < numTargets(); ++i) target_start_.push_back(targetPosition(i));
  // The first dynamic step's factor is part of loading the scene, as a mesh change's is part
  // of its background build: step 1 costs what any step does.
  if (scene.solver.mode == SolverSettings::Mode::Dynamic) tissue_->prepareForSteps(dt_, {});
  // So are the SPR patch fits of the first mesh (30 ms on the DBS mesh at the first pass).
  if (adaptation_ && !estimator_) estimator_ = std::make_unique<SprEstimator>(tissue_->model());
}

namespace {
std::atomic<double> g_rebuild_delay_ms{0.0};
std::atomic<int> g_setup_threads{0};
}  // namespace

void Simulation::setSetupThreads(int n) { g_setup_threads = std::max(n, 0); }
int Simulation::setupThreads() { return g_setup_threads; }

void Simulation::setRebuildDelayForTesting(double ms) { g_rebuild_delay_ms = ms; }

void Simulation::replanNeedles() {
  const int t = findTarget(scene_.brain_shift->target);
  const Vec3 shift = targetPosition(t) - targets_[t].planned;
  replans_.clear();
  for (size_t n = 0; n < needles_.size(); ++n) {
    const NeedleParameters& planned = scene_.needles[n];
    TrajectoryReplan r;
    try {
      r = replanFor(planned, shift);
    } catch (const std::invalid_argument& e) {
      throw InputError(scene_.file, "brain_shift.replan", e.what());
    }
    replans_.push_back(r);
    // Still at rest and out of the tissue: a body on the new plan replaces the old one.
    needles_[n] = std::make_unique<NeedleBody>(replanned(planned, r), scene_.solver);
  }
  if (interaction_) {
    std::vector<NeedleBody*> nd;
    for (auto& n : needles_) nd.push_back(n.get());
    interaction_ = std::make_unique<NeedleTissueInteraction>(*scene_.interaction, *tissue_, nd, organ_.get());
  }
}

Simulation::Simulation(const Simulation& o)
    : scene_((o.waitForPass(true), o.scene_)),  // a background pass has finished with what is copied
      dt_(o.dt_),
      probes_(o.probes_),
      targets_(o.targets_),
      target_start_(o.target_start_),
      immersed_(o.immersed_),
      cell_fraction_(o.cell_fraction_),
      shift_result_(o.shift_result_),
      replans_(o.replans_),
      reference_(o.reference_),
      levels_(o.levels_),
      hanging_nodes_(o.hanging_nodes_),
      deferred_rebuilds_(o.deferred_rebuilds_),
      rebuild_waits_(o.rebuild_waits_),
      background_passes_(o.background_passes_),
      pass_waits_(o.pass_waits_),
      passes_after_decision_(o.passes_after_decision_),
      estimate_(o.estimate_),
      estimate_step_(-1),
      estimate_ever_(o.estimate_ever_),
      options_(o.options_),
      target_errors_(o.target_errors_),
      target_errors_step_(-1),
      errors_ever_(o.errors_ever_),
      last_error_step_(o.last_error_step_),
      target_error_steps_(o.target_error_steps_.size(), -1),
      shifted_(o.shifted_),
      shift_errors_(o.shift_errors_),
      qoi_radius_(o.qoi_radius_),
      goal_targets_(o.goal_targets_),
      contact_signature_(o.contact_signature_),
      contact_states_(o.contact_states_),
      pass_due_(o.pass_due_),
      step_(o.step_),
      step_base_(o.step_base_),
      time_base_(o.time_base_),
      every_steps_(o.every_steps_),
      last_(o.last_),
      diag_(o.diag_) {
  for (const auto& n : o.needles_) needles_.push_back(std::make_unique<NeedleBody>(*n));
  if (!o.tissue_) return;
  tissue_ = std::make_unique<TissueBody>(*o.tissue_);
  if (o.organ_) organ_ = std::make_unique<EmbeddedSurface>(o.organ_->restPtr(), tissue_->mesh());
  if (o.shift_) {
    shift_ = std::make_unique<BrainShift>(*o.shift_);
    shift_->rebind(organ_.get());
  }
  if (o.adaptation_) adaptation_ = std::make_unique<MeshAdaptation>(*o.adaptation_);
  if (o.pending_rebuild_) {
    // The copy switches at the same step to a copy of the same body (finished here, so that
    // both step alike whatever the thread's timing).
    const std::shared_ptr<PreparedTissue> q = copyPrepared(*o.pending_rebuild_->job.get());
    std::promise<std::shared_ptr<PreparedTissue>> ready;
    ready.set_value(q);
    pending_rebuild_ = std::make_unique<PendingRebuild>(*o.pending_rebuild_);
    pending_rebuild_->job = ready.get_future().share();
  }
  if (o.pending_pass_) {
    // The same decision (finished: waited for above), taken up at the same step; a body it
    // built is copied as a pending rebuild's is.
    pending_pass_ = std::make_unique<PendingPass>(*o.pending_pass_);
    const std::shared_ptr<PreparedTissue> p = o.pending_pass_->build.get();
    std::shared_ptr<PreparedTissue> q;
    if (p) q = copyPrepared(*p);
    std::promise<std::shared_ptr<PreparedTissue>> ready;
    ready.set_value(q);
    pending_pass_->build = ready.get_future().share();
  }
  if (o.interaction_) {
    std::vector<NeedleBody*> nd;
    for (auto& n : needles_) nd.push_back(n.get());
    interaction_ = std::make_unique<NeedleTissueInteraction>(*o.interaction_, *tissue_, nd, organ_.get());
  }
  // The estimator binds to the tissue body: made again on first use (estimate_step_ = -1,
  // the same estimate results from the same state).
}

Simulation::~Simulation() {
  // The background build reads the scene: it finishes before the simulation goes.
  if (pending_rebuild_ && pending_rebuild_->job.valid()) pending_rebuild_->job.wait();
  waitForPass(true);
}

void Simulation::setTimeStep(double dt) {
  if (!(dt > 0) || !std::isfinite(dt)) throw std::invalid_argument("time step must be positive and finite");
  time_base_ = time();
  step_base_ = step_;
  dt_ = dt;
}

void Simulation::preStep() {
  const auto t0 = steadyNow();
  shift_ = std::make_unique<BrainShift>(*scene_.brain_shift, scene_.tissue, organ_.get());
  const int t = scene_.brain_shift->target.empty() ? -1 : findTarget(scene_.brain_shift->target);
  BrainShiftResult total;
  double scale = 1.0;
  // On an adaptive mesh: solve, estimate, refine/coarsen, and solve again on the new mesh
  // (from the shifted state and the last load scale) until the mesh stays as it is, so the
  // insertion starts from the shift computed on the mesh the estimate asks for.
  // The passes before the last solve roughly (the estimate needs the stress pattern, not
  // the last digit); the last one, on the final mesh, solves to the tolerance and scales the
  // load for target_shift, starting from the rough pass's state.
  bool rough = adaptation_ != nullptr;
  // A uniformly refined grid starts from the shift solved on the grid one level coarser:
  // the controlled solve there finds the load scale and most of the skull's contact set at a
  // fraction of the cost (nested iteration; doc/method.md "Brain shift"). Its counts and
  // times are part of the totals.
  BrainShiftResult coarse = adaptation_ ? BrainShiftResult{} : coarseShiftStart(t);
  if (coarse.coarse_dofs > 0) {
    scale = coarse.coarse_load_scale;
    total.newton_iterations = coarse.newton_iterations;
    total.factorizations = coarse.factorizations;
    total.load_solves = coarse.load_solves;
    total.multiplier_updates = coarse.multiplier_updates;
    total.factor_ms = coarse.factor_ms;
    total.solve_ms = coarse.solve_ms;
  }
  for (int pass = 1;; ++pass) {
    // The coarse mesh's first pass only shows where to refine: its load scale (which the
    // refined meshes change severalfold, the clamps holding more nodes) is not solved for.
    auto solve = [&] {
      return shift_->apply(*tissue_, t >= 0 ? &targets_[t].point : nullptr, scale, rough, !(rough && pass == 1));
    };
    BrainShiftResult r;
    try {
      r = solve();
    } catch (const NumericalError&) {
      if (coarse.coarse_dofs == 0) throw;
      // The coarse start led the solve astray: from rest, as without it.
      tissue_->setState(tissue_->mesh().restPositions(), VecX::Zero(tissue_->mesh().numDofs()));
      tissue_->resetExternalForce();
      shift_ = std::make_unique<BrainShift>(*scene_.brain_shift, scene_.tissue, organ_.get());
      coarse = BrainShiftResult{};
      total = BrainShiftResult{};
      scale = 1.0;
      r = solve();
    }
    const int iterations = total.newton_iterations + r.newton_iterations;
    const int factorizations = total.factorizations + r.factorizations;
    const int solves = total.load_solves + r.load_solves, updates = total.multiplier_updates + r.multiplier_updates;
    const double fms = total.factor_ms + r.factor_ms, sms = total.solve_ms + r.solve_ms;
    total = r;
    total.newton_iterations = iterations;
    total.factorizations = factorizations;
    total.load_solves = solves;
    total.multiplier_updates = updates;
    total.factor_ms = fms;
    total.solve_ms = sms;
    total.passes = pass;
    scale = r.load_scale;
    checkState();
    if (!rough) break;
    const AdaptationResult a = pass < kMaxShiftPasses ? adaptationPass() : AdaptationResult{};
    if (a.changed) {
      rebuildTissue(false);
    } else {
      // Final solve on this mesh, from the rough state (apply adds its loads afresh).
      rough = false;
      tissue_->resetExternalForce();
    }
    shift_->rebind(organ_.get());
  }
  if (t >= 0) total.target = scene_.brain_shift->target;
  // The shift's own error on the targets, before the estimate's reference becomes the
  // shifted state (the insertion's estimates add it).
  if (options_.target_errors && numTargets() > 0) {
    shift_errors_ = targetErrors();
    // target_shift prescribes the length of that target's shift, not its direction: the
    // estimate loses its component along the shift (the load scale makes that one exact), the
    // bound is kept whole (a bound on the full error bounds its part across the shift). Before
    // (2026-12-02) the whole error was dropped, and the DBS study showed the STN's bound
    // missing the shift's direction error (0.5-0.8 mm against the 4 mm mesh).
    if (t >= 0 && scene_.brain_shift->target_shift && shift_errors_[t].valid) {
      const Vec3 d = total.target_displacement.norm() > 0 ? Vec3(total.target_displacement.normalized()) : Vec3::Zero();
      TargetError& e = shift_errors_[t];
      e.estimate -= e.estimate.dot(d) * d;
    }
    shifted_ = tissue_->positions();
    forgetEstimates();
  }
  applySupport();
  if (adaptation_) {
    // From now on the mesh adapts to the insertion: the estimate measures the stress change
    // since the shift, and the shift's refinement stays.
    adaptation_->keepCurrentRefinement();
    reference_ = tissue_->positions();
    forgetEstimates();
  }
  total.ms = msSince(t0);
  total.coarse_dofs = coarse.coarse_dofs;
  total.coarse_newton_iterations = coarse.newton_iterations;
  total.coarse_factorizations = coarse.factorizations;
  total.coarse_ms = coarse.ms;
  total.coarse_load_scale = coarse.coarse_load_scale;
  shift_result_ = total;
}

BrainShiftResult Simulation::coarseShiftStart(int target) {
  const BrainShiftSettings& settings = *scene_.brain_shift;
  const ImmersedGridSettings& fine = scene_.tissue.geometry.grid;
  if (!settings.coarse_start || !immersed_ || fine.refine < 1 || target < 0 || !settings.target_shift) return {};
  const auto t0 = steadyNow();
  ImmersedGridSettings g = fine;
  --g.refine;  // the same origin and box: this grid's nodes lie in its box
  std::unique_ptr<TissueBody> coarse;
  BrainShiftResult r;
  // An optional speed-up: whatever fails on the coarse grid (a clamp region selecting none
  // of its nodes, a solve that does not converge, a degenerate mesh) means no start, and
  // this grid solves from rest as without it.
  try {
    const ImmersedGrid grid(scene_.tissue.geometry.surface, g);
    coarse = std::make_unique<TissueBody>(grid.mesh(), scene_.tissue, scene_.solver, scene_.file);
    const EmbeddedSurface organ(scene_.tissue.geometry.surface, coarse->mesh());
    BrainShift shift(settings, scene_.tissue, &organ);
    const PointLocator locator(coarse->mesh());
    EmbeddedPoint point;
    const Vec3& rest = targets_[target].point.rest;
    if (!locator.locate(rest, point) && !locator.locateNearest(rest, point)) return {};
    // Rough (to 1e-3, penetrations to 1 % of the gap), the load scaled to the target shift.
    r = shift.apply(*coarse, &point, 1.0, true, true);
  } catch (const std::runtime_error&) {  // InputError, NumericalError, CHOLMOD's failures
    return {};
  } catch (const std::invalid_argument&) {
    return {};
  }
  const TissueBody& body = *coarse;
  const PointLocator locator(body.mesh());
  auto embed = [&](const Vec3& p, EmbeddedPoint& ep) { return locator.locate(p, ep) || locator.locateNearest(p, ep); };
  // Its displacements, interpolated at this grid's nodes (the clamped ones keep theirs; one
  // outside the coarse grid's kept cells, which sample the surface more coarsely, takes the
  // nearest cell's).
  const VecX u = body.displacements();
  VecX x = tissue_->positions();
  for (int i = 0; i < tissue_->mesh().numNodes(); ++i) {
    EmbeddedPoint ep;
    const Vec3 p = node3(x, i);
    if (embed(p, ep)) node3(x, i) = p + ep.interpolate(body.mesh(), u);
  }
  tissue_->setState(x, VecX::Zero(x.size()));
  checkState();
  r.coarse_dofs = body.mesh().numDofs();
  r.coarse_load_scale = r.load_scale;
  r.ms = msSince(t0);
  return r;
}

void Simulation::applySupport() { support(shift_.get(), *tissue_, organ_.get()); }

void Simulation::support(const BrainShift* shift, TissueBody& body, const EmbeddedSurface* organ) {
  if (!shift || !organ || !shift->hasSupport()) return;
  body.setSupport(shift->supportStiffness(*organ));
  body.addExternalForce(shift->supportAnchorLoad(body, *organ));
}

void Simulation::setFractions(HexMesh& mesh, const std::vector<int>& cells) {
  const RefinableHexMesh& forest = adaptation_->forest();
  std::vector<double> f(mesh.numElements());
  for (int e = 0; e < mesh.numElements(); ++e) {
    auto it = cell_fraction_.find(cells[e]);
    if (it == cell_fraction_.end()) {
      // A child of a cell wholly inside is wholly inside; others are sampled.
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

EmbeddedPoint Simulation::embedPoint(const PointLocator& locator, const Vec3& p, const std::string& file,
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

void Simulation::embedProbes() { embedProbes(PointLocator(tissue_->mesh())); }

void Simulation::embedProbes(const PointLocator& locator) {
  probes_.clear();
  for (size_t i = 0; i < scene_.probes.size(); ++i)
    probes_.push_back(
        embedPoint(locator, scene_.probes[i].point, scene_.file, "probes[" + std::to_string(i) + "].point", "point"));
}

void Simulation::embedTargets() { embedTargets(PointLocator(tissue_->mesh())); }

void Simulation::embedTargets(const PointLocator& locator) {
  for (auto& t : targets_) {  // (again after a mesh change: by their planning positions)
    const bool from_scene = t.key != "set_target";
    t.point = embedPoint(locator, t.planned, from_scene ? scene_.file : "",
                         from_scene ? t.key + (t.surface ? ".surface" : ".point") : "set_target.point",
                         t.surface ? "the surface's centroid" : "point");
  }
}

int Simulation::setTarget(const std::string& name, const Vec3& point) {
  if (name.empty()) throw InputError("", "set_target.name", "must not be empty");
  if (!tissue_) throw InputError("", "set_target", "the scene has no tissue");
  if (!point.allFinite()) throw InputError("", "set_target.point", "must be finite");
  const EmbeddedPoint ep = embedPoint(PointLocator(tissue_->mesh()), point, "", "set_target.point", "point");
  int i = findTarget(name);
  if (i < 0) {
    i = numTargets();
    targets_.push_back({name, point, ep, "set_target", nullptr});
    target_start_.push_back(Vec3::Zero());
  } else {
    targets_[i] = {name, point, ep, "set_target", nullptr};
  }
  qois_.clear();  // (a new or moved target: its regularised point is made again)
  target_error_steps_.assign(target_error_steps_.size(), -1);
  target_start_[i] = targetPosition(i);
  return i;
}

int Simulation::findTarget(const std::string& name) const {
  for (int i = 0; i < numTargets(); ++i)
    if (targets_[i].name == name) return i;
  return -1;
}

Vec3 Simulation::targetPosition(int i) const {
  return targets_[i].point.interpolate(tissue_->mesh(), tissue_->positions());
}

Vec3 Simulation::targetVelocity(int i) const {
  return targets_[i].point.interpolate(tissue_->mesh(), tissue_->velocities());
}

void Simulation::applyPersistentLoads() { persistentLoads(shift_.get(), shift_result_.load_scale, *tissue_, organ_.get()); }

void Simulation::persistentLoads(const BrainShift* shift, double load_scale, TissueBody& body,
                                 const EmbeddedSurface* organ) {
  if (!shift) return;
  VecX f = load_scale * shift->unitLoad(body);
  if (organ) f += shift->skullLoad(body, *organ);
  body.addExternalForce(f);
  support(shift, body, organ);
}

std::vector<int> Simulation::elementLevels() const {
  if (adaptation_) return levels_;
  return std::vector<int>(tissue_ ? tissue_->mesh().numElements() : 0, 0);
}

std::vector<int> Simulation::elementsPerLevel() const {
  std::vector<int> n((adaptation_ ? adaptation_->settings().max_level : 0) + 1, 0);
  if (!adaptation_) {
    n[0] = tissue_ ? tissue_->mesh().numElements() : 0;
    return n;
  }
  for (int l : levels_)
    if (l >= 0 && l < static_cast<int>(n.size())) ++n[l];
  return n;
}

void Simulation::noteActiveMesh() {
  if (!adaptation_) return;
  levels_ = adaptation_->active().level;
  hanging_nodes_ = adaptation_->active().numHanging();
}

const ErrorEstimate& Simulation::errorEstimate() const {
  if (estimate_step_ != step_) {
    waitForPass(false);  // the estimator is a background pass's until its decision is made
    estimate_ever_ = true;
    if (!estimator_) estimator_ = std::make_unique<SprEstimator>(tissue_->model());
    estimate_ = estimator_->estimate(tissue_->positions(), reference_.size() ? &reference_ : nullptr);
    estimate_step_ = step_;
  }
  return estimate_;
}

void Simulation::forgetEstimates() {
  estimator_.reset();
  estimate_step_ = -1;
  qois_.clear();
  duals_.clear();
  target_errors_step_ = -1;
  goal_primal_step_ = -1;
  target_error_steps_.assign(target_error_steps_.size(), -1);
}

double Simulation::qoiRadius(int i) const {
  const double r = i < static_cast<int>(scene_.targets.size()) && targets_[i].key != "set_target" ? scene_.targets[i].radius : -1;
  return r >= 0 ? r : qoi_radius_;
}

const TargetError& Simulation::targetError(int i) const {
  if (target_errors_.size() != targets_.size() || target_error_steps_.size() != targets_.size()) {
    target_errors_.resize(targets_.size());
    target_error_steps_.resize(targets_.size(), -1);
  }
  if (target_error_steps_[i] == step_ && target_errors_step_ != -1) return target_errors_[i];
  waitForPass(false);
  const HexMesh& mesh = tissue_->mesh();
  if (qois_.size() != targets_.size()) {
    const PointLocator locator(mesh);
    qois_.clear();
    for (int k = 0; k < numTargets(); ++k) qois_.push_back(targetQoi(mesh, locator, targets_[k].planned, qoiRadius(k)));
  }
  // The field the estimate is of: the change since the brain shift when there was one (the
  // insertion's), else the displacement from rest. On an adaptive mesh that is also the SPR
  // estimate's reference; on a uniform one the primal estimate is made for it here.
  const VecX* ref = reference_.size() ? &reference_ : shifted_.size() ? &shifted_ : nullptr;
  const ErrorEstimate* primal = &errorEstimate();  // (and estimator_ for this mesh)
  if (ref && ref != &reference_) {
    if (goal_primal_step_ != step_) {
      goal_primal_ = estimator_->estimate(tissue_->positions(), ref);
      goal_primal_step_ = step_;
    }
    primal = &goal_primal_;
  }
  if (duals_.size() != targets_.size()) duals_.resize(targets_.size());
  Eigen::MatrixXd& Z = duals_[i];  // the last pass's on this mesh: CG starts from it
  int iterations = 0;
  TargetError e;
  if (tissue_->solveDual(qois_[i].load(mesh), Z, iterations))
    e = goalEstimate(*estimator_, tissue_->positions(), ref, *primal, Z, qois_[i], mesh, mesh.restPositions());
  e.dual_iterations = iterations;
  // After a brain shift the estimate is of the change since; the shift's own error adds
  // (errors add, so do their bounds). A shift scaled by target_shift prescribes that
  // target's displacement: its error is in the load scale, not added.
  if (e.valid && ref && i < static_cast<int>(shift_errors_.size()) && shift_errors_[i].valid) {
    e.estimate += shift_errors_[i].estimate;
    e.component_bound += shift_errors_[i].component_bound;
    e.bound += shift_errors_[i].bound;
  }
  if (e.valid && ref && i < static_cast<int>(shift_errors_.size())) e.qoi += shift_errors_[i].qoi;
  target_errors_[i] = std::move(e);
  target_error_steps_[i] = step_;
  target_errors_step_ = step_;
  last_error_step_ = step_;
  errors_ever_ = true;
  return target_errors_[i];
}

const std::vector<TargetError>& Simulation::targetErrors() const {
  for (int i = 0; i < numTargets(); ++i) targetError(i);
  return target_errors_;
}

AdaptationResult Simulation::adaptationPass() {
  const ErrorEstimate& est = errorEstimate();
  if (goal_targets_.empty()) return adaptation_->adapt(est);
  // Goal-oriented: the element indicators of the controlled targets, each relative to the
  // tolerance; refinement only while a target's bound is above it.
  const double tol = scene_.adaptivity->goal_tolerance;
  ErrorEstimate goal;
  goal.eta.assign(est.eta.size(), 0.0);
  bool refine = false;
  for (int t : goal_targets_) {
    const TargetError& e = targetError(t);
    if (!e.valid) {
      refine = true;  // no estimate: fall back on the energy estimate's pattern
      for (size_t k = 0; k < goal.eta.size(); ++k) goal.eta[k] += est.eta[k] / std::max(est.max, 1e-300);
      continue;
    }
    refine = refine || e.bound > tol;
    for (size_t k = 0; k < goal.eta.size(); ++k) goal.eta[k] += e.indicator[k] / tol;
  }
  double sum = 0;
  for (double v : goal.eta) {
    goal.max = std::max(goal.max, v);
    sum += v * v;
  }
  goal.global = std::sqrt(sum);
  return adaptation_->adapt(goal, refine);
}

void Simulation::rebuildTissue(bool persistent_loads) {
  const VecX x = adaptation_->transfer(tissue_->positions());
  const VecX v = persistent_loads ? adaptation_->transfer(tissue_->velocities()) : VecX::Zero(x.size());
  if (reference_.size()) reference_ = adaptation_->transfer(reference_);
  if (shifted_.size()) shifted_ = adaptation_->transfer(shifted_);
  const auto& act = adaptation_->active();
  forgetEstimates();
  HexMesh mesh = act.mesh;
  if (immersed_) setFractions(mesh, act.cell);
  tissue_ = std::make_unique<TissueBody>(std::move(mesh), scene_.tissue, scene_.solver, scene_.file, act.hanging);
  tissue_->setState(x, v);
  if (immersed_) organ_ = std::make_unique<EmbeddedSurface>(scene_.tissue.geometry.surface, tissue_->mesh());
  if (persistent_loads) applyPersistentLoads();
  embedProbes();
  embedTargets();
  if (interaction_) interaction_->rebind(*tissue_, organ_.get());
  noteActiveMesh();
}

void Simulation::startRebuild() {
  // On this thread: the state carried to the new mesh (a transfer, cheap), its volume
  // fractions (cached per cell), and where the constraint points are. The rest, which is
  // most of a rebuild (DOF map, assembly pattern, factor, compliance columns, the organ's
  // embedding), on a background thread, from values it owns.
  const auto& act = adaptation_->active();
  auto pending = std::make_unique<PendingRebuild>();
  pending->switch_step = step_ + rebuildLagSteps();
  pending->levels = act.level;
  pending->hanging = act.numHanging();
  HexMesh mesh = act.mesh;
  if (immersed_) setFractions(mesh, act.cell);
  VecX x = adaptation_->transfer(tissue_->positions()), v = adaptation_->transfer(tissue_->velocities());
  std::vector<Vec3> points;
  if (interaction_)
    for (const auto& c : interaction_->constraints()) points.push_back(c->tissue.rest);
  auto hanging = act.hanging;
  const Scene* scene = &scene_;
  const double h = dt_;
  const BrainShift* shift = shift_.get();  // frozen after the pre-step: read only
  const double load_scale = shift_result_.load_scale;
  tissue_->holdFactorRefresh(true);  // the build gets the second core (the DBS switch waited for it)
  pending->job = std::async(std::launch::async,
                            [scene, h, shift, load_scale, mesh = std::move(mesh), hanging = std::move(hanging),
                             x = std::move(x), v = std::move(v), points = std::move(points),
                             retired = std::move(retired_tissue_)]() mutable {
                              lowerThisThreadPriority();
                              nameThisThread("ns_rebuild");
                              retired.reset();  // the body the last switch replaced: freed here
                              return prepareTissue(*scene, h, shift, load_scale, std::move(mesh), std::move(hanging),
                                                   x, v, points);
                            })
                     .share();
  pending_rebuild_ = std::move(pending);
  ++deferred_rebuilds_;
}

std::shared_ptr<Simulation::PreparedTissue> Simulation::copyPrepared(const PreparedTissue& p) {
  auto q = std::make_shared<PreparedTissue>();
  q->tissue = std::make_unique<TissueBody>(*p.tissue);
  if (p.organ) q->organ = std::make_unique<EmbeddedSurface>(p.organ->restPtr(), q->tissue->mesh());
  // Its lookups are made at its own switch (finishRebuild), on the thread that steps the copy
  // (a prediction's): a copy taken on the stepping thread for an estimate never gets there.
  return q;
}

std::shared_ptr<Simulation::PreparedTissue> Simulation::prepareTissue(const Scene& scene, double h,
                                                                      const BrainShift* shift, double load_scale,
                                                                      HexMesh mesh, HangingNodes hanging, const VecX& x,
                                                                      const VecX& v, const std::vector<Vec3>& points) {
  auto p = std::make_shared<PreparedTissue>();
  p->tissue = std::make_unique<TissueBody>(std::move(mesh), scene.tissue, scene.solver, scene.file, hanging);
  p->tissue->setState(x, v);
  const HexMesh& m = p->tissue->mesh();
  if (scene.tissue.geometry.kind == TissueGeometry::Kind::Surface)
    p->organ = std::make_unique<EmbeddedSurface>(scene.tissue.geometry.surface, m);
  persistentLoads(shift, load_scale, *p->tissue, p->organ.get());
  p->locator = std::make_unique<PointLocator>(m);
  const PointLocator& locator = *p->locator;
  std::vector<int> elements;
  for (const Vec3& r : points) {
    EmbeddedPoint ep;
    if (locator.locate(r, ep) || locator.locateNearest(r, ep)) elements.push_back(ep.element);
  }
  std::sort(elements.begin(), elements.end());
  elements.erase(std::unique(elements.begin(), elements.end()), elements.end());
  p->tissue->prepareForSteps(h, elements);
  p->estimator = std::make_unique<SprEstimator>(p->tissue->model());
  if (scene.interaction) p->binding = TissueBinding::make(m, p->organ.get());
  const double delay = g_rebuild_delay_ms;
  if (delay > 0) std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(delay));
  return p;
}

void Simulation::startPass() {
  // On this thread: copies of what the pass reads (positions, velocities, the rotation
  // guesses the estimate's polar decompositions start from, the constraint points). The
  // estimator and the forest are the background thread's until the decision is taken up
  // (waitForPass); the tissue body steps on meanwhile.
  if (!estimator_) estimator_ = std::make_unique<SprEstimator>(tissue_->model());
  auto pp = std::make_unique<PendingPass>();
  pp->step = step_;
  pp->take_step = step_ + estimateLagSteps();
  pp->switch_step = step_ + std::max(rebuildLagSteps(), estimateLagSteps());
  std::vector<Vec3> points;
  if (interaction_)
    for (const auto& c : interaction_->constraints()) points.push_back(c->tissue.rest);
  std::promise<std::shared_ptr<const PassDecision>> decided;
  pp->decision = decided.get_future().share();
  const SprEstimator* estimator = estimator_.get();
  MeshAdaptation* adaptation = adaptation_.get();
  const VecX* reference = reference_.size() ? &reference_ : nullptr;  // changes only at a switch
  const double h = dt_;
  const BrainShift* shift = shift_.get();
  const double load_scale = shift_result_.load_scale;
  pp->build =
      std::async(std::launch::async,
                 [this, estimator, adaptation, reference, h, shift, load_scale, decided = std::move(decided),
                  retired = std::move(retired_tissue_),
                  x = VecX(tissue_->positions()), v = VecX(tissue_->velocities()),
                  guesses = tissue_->model().rotationGuesses(), points = std::move(points)]() mutable
                 -> std::shared_ptr<PreparedTissue> {
                   lowerThisThreadPriority();
                   nameThisThread("ns_adapt");
                   retired.reset();  // here, not on the stepping thread
                   HexMesh mesh;
                   HangingNodes hanging;
                   VecX xt, vt;
                   try {
                     auto d = std::make_shared<PassDecision>();
                     const auto t0 = steadyNow();
                     d->estimate = estimator->estimate(x, reference, &guesses);
                     const auto t1 = steadyNow();
                     d->result = adaptation->adapt(d->estimate);
                     if (d->result.changed) {
                       const auto& act = adaptation->active();
                       d->levels = act.level;
                       d->hanging = act.numHanging();
                       mesh = act.mesh;
                       if (immersed_) setFractions(mesh, act.cell);
                       hanging = act.hanging;
                       xt = adaptation->transfer(x);
                       vt = adaptation->transfer(v);
                     }
                     d->estimate_ms = msBetween(t0, t1);
                     d->mark_refine_ms = msSince(t1);
                     const double delay = g_rebuild_delay_ms;  // tests: a late pass
                     if (delay > 0) std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(delay));
                     const bool changed = d->result.changed;
                     decided.set_value(std::move(d));  // from here on, nothing of the simulation's is touched
                     if (!changed) return nullptr;
                   } catch (...) {
                     decided.set_exception(std::current_exception());
                     return nullptr;
                   }
                   return prepareTissue(scene_, h, shift, load_scale, std::move(mesh), std::move(hanging), xt, vt,
                                        points);
                 })
          .share();
  pending_pass_ = std::move(pp);
  ++background_passes_;
}

void Simulation::takePass() {
  PendingPass& pp = *pending_pass_;
  if (pp.decision.wait_for(std::chrono::seconds(0)) != std::future_status::ready) ++pass_waits_;
  const std::shared_ptr<const PassDecision> d = pp.decision.get();  // rethrows the pass's error
  estimate_ = d->estimate;  // the last one made (of the pass's step, not of this one)
  estimate_ever_ = true;
  last_.refined += d->result.refined;
  last_.coarsened += d->result.coarsened;
  if (d->result.changed) {
    auto pending = std::make_unique<PendingRebuild>();
    pending->switch_step = pp.switch_step;
    pending->levels = d->levels;
    pending->hanging = d->hanging;
    pending->job = pp.build;
    tissue_->holdFactorRefresh(true);
    pending_rebuild_ = std::move(pending);
    ++deferred_rebuilds_;
  }
  pending_pass_.reset();
}

long Simulation::estimateLagSteps() const {
  const double d = scene_.adaptivity ? scene_.adaptivity->estimate_delay : 0.0;
  return d > 0 ? std::max(1L, std::lround(d / dt_)) : 0;
}

void Simulation::waitForPass(bool build) const {
  if (!pending_pass_) return;
  pending_pass_->decision.wait();
  if (build && pending_pass_->build.valid()) pending_pass_->build.wait();
}

long Simulation::rebuildLagSteps() const {
  const double d = scene_.adaptivity ? scene_.adaptivity->rebuild_delay : 0.0;
  return d > 0 ? std::max(1L, std::lround(d / dt_)) : 0;
}

void Simulation::finishRebuild() {
  const auto t0 = steadyNow();
  PendingRebuild& pr = *pending_rebuild_;
  if (pr.job.wait_for(std::chrono::seconds(0)) != std::future_status::ready) ++rebuild_waits_;
  std::shared_ptr<PreparedTissue> p = pr.job.get();
  // The state of now, carried over; the body keeps the factor and columns made for it.
  const VecX x = adaptation_->transfer(tissue_->positions());
  const VecX v = adaptation_->transfer(tissue_->velocities());
  if (reference_.size()) reference_ = adaptation_->transfer(reference_);
  if (shifted_.size()) shifted_ = adaptation_->transfer(shifted_);
  forgetEstimates();
  retired_tissue_ = std::move(tissue_);  // freed on the next pass's or build's thread
  tissue_ = std::move(p->tissue);
  tissue_->setState(x, v);
  if (immersed_) organ_ = std::move(p->organ);
  estimator_ = std::move(p->estimator);  // (its loads and support were applied in the build)
  if (!p->locator) p->locator = std::make_unique<PointLocator>(tissue_->mesh());  // (a copy's)
  embedProbes(*p->locator);
  embedTargets(*p->locator);
  if (interaction_) {
    if (p->binding.locator) interaction_->rebind(*tissue_, std::move(p->binding));
    else interaction_->rebind(*tissue_, organ_.get());
  }
  levels_ = std::move(pr.levels);
  hanging_nodes_ = pr.hanging;
  pending_rebuild_.reset();
  last_.mesh_changed = true;
  last_.rebuild_ms += msSince(t0);
}

AdaptationResult Simulation::refineElements(const std::vector<int>& elements) {
  if (!adaptation_) throw std::logic_error("refineElements: the scene has no adaptivity section");
  if (pending_pass_) takePass();
  if (pending_rebuild_) finishRebuild();
  const AdaptationResult r = adaptation_->refineElements(elements);
  if (r.changed) rebuildTissue();
  return r;
}

AdaptationResult Simulation::coarsenElements(const std::vector<int>& elements) {
  if (!adaptation_) throw std::logic_error("coarsenElements: the scene has no adaptivity section");
  if (pending_pass_) takePass();
  if (pending_rebuild_) finishRebuild();
  const AdaptationResult r = adaptation_->coarsenElements(elements);
  if (r.changed) rebuildTissue();
  return r;
}

void Simulation::adaptMesh(bool defer) {
  // A pass estimates the mesh the last pass decided on: a deferred change switches first.
  if (pending_pass_) takePass();
  if (pending_rebuild_) finishRebuild();
  if (defer && estimateLagSteps() > 0 && goal_targets_.empty()) {
    const auto t0 = steadyNow();
    startPass();
    last_.adapted = true;
    last_.estimate_ms = msSince(t0);  // this thread's share: the copies
    return;
  }
  const auto t0 = steadyNow();
  errorEstimate();
  for (int t : goal_targets_) targetError(t);
  const auto t1 = steadyNow();
  const AdaptationResult r = adaptationPass();
  const auto t2 = steadyNow();
  const bool deferred = r.changed && defer && rebuildLagSteps() > 0;
  if (deferred) startRebuild();
  else if (r.changed) rebuildTissue();
  const auto t3 = steadyNow();
  last_.adapted = true;
  last_.mesh_changed = last_.mesh_changed || (r.changed && !deferred);
  last_.refined = r.refined;
  last_.coarsened = r.coarsened;
  last_.estimate_ms = msBetween(t0, t1);
  last_.mark_refine_ms = msBetween(t1, t2);
  last_.rebuild_ms += msBetween(t2, t3);
}

Vec3 Simulation::probeDisplacement(int i) const {
  const auto& ep = probes_[i];
  return ep.interpolate(tissue_->mesh(), tissue_->positions()) - ep.rest;
}

int Simulation::numDofs() const {
  int n = tissue_ ? tissue_->mesh().numDofs() : 0;
  for (const auto& nd : needles_) n += nd->numDofs();
  return n;
}

int Simulation::numElements() const {
  int n = tissue_ ? tissue_->mesh().numElements() : 0;
  for (const auto& nd : needles_) n += nd->beam().numElements();
  return n;
}

double Simulation::kineticEnergy() const {
  double e = tissue_ ? tissue_->kineticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->kineticEnergy();
  return e;
}

double Simulation::elasticEnergy() const {
  double e = tissue_ ? tissue_->elasticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->elasticEnergy();
  return e;
}

void Simulation::checkState() const {
  for (const auto& nd : needles_) {
    for (int i = 0; i < nd->beam().numNodes(); ++i)
      if (!nd->state().p[i].allFinite() || !nd->state().q[i].coeffs().allFinite())
        throw NumericalError(step_, "needle '" + nd->name() + "': non-finite state at step " + std::to_string(step_));
    const double reach = (nd->tipPosition() - nd->state().p[0]).norm();
    if (reach > 2 * nd->beam().length())
      throw NumericalError(step_, "needle '" + nd->name() + "' diverged at step " + std::to_string(step_) +
                                      ": tip " + std::to_string(reach) + " m from the base");
  }
  if (!tissue_) return;
  const VecX& x = tissue_->positions();
  const VecX& v = tissue_->velocities();
  if (!x.allFinite() || !v.allFinite())
    throw NumericalError(step_, "non-finite positions or velocities at step " + std::to_string(step_));
  const double umax = tissue_->displacements().lpNorm<Eigen::Infinity>();
  if (umax > 10 * diag_)
    throw NumericalError(step_, "divergence at step " + std::to_string(step_) + ": displacement " +
                                    std::to_string(umax) + " m exceeds 10x the tissue size");
}

const StepStats& Simulation::step() {
  const long k = step_ + 1;
  try {
    const bool dynamic = scene_.solver.mode == SolverSettings::Mode::Dynamic;
    last_ = StepStats{};
    auto add = [&](const StepStats& s) { last_.accumulate(s); };
    if (interaction_) {
      // free motion of every body, constraint solve and corrections, commit, law updates
      const double h = dt_;
      add(tissue_->freeMotion(h));
      for (auto& nd : needles_) add(nd->freeMotion(time(), h));
      const InteractionStats is = interaction_->solve(h);
      last_.constraint_points = is.points;
      last_.constraint_iterations = is.iterations;
      last_.constraint_residual = is.residual;
      last_.constraint_converged = is.converged;
      last_.constraint_ms = is.ms;
      tissue_->commit(h);
      for (auto& nd : needles_) nd->commit(time(), h);
      interaction_->afterCommit();
    } else {
      if (tissue_) add(dynamic ? tissue_->stepDynamic(dt_) : tissue_->solveStatic());
      for (auto& nd : needles_) add(dynamic ? nd->stepDynamic(time(), dt_) : nd->solveStatic(time() + dt_));
      // A static load step on an adaptive mesh: solve, estimate, adapt and solve again on
      // the new mesh until it stays as it is (the state a step ends in is an equilibrium
      // on the mesh it is reported on).
      if (!dynamic && tissue_ && adaptation_)
        for (int pass = 1; pass < kMaxShiftPasses; ++pass) {
          last_.mesh_changed = false;
          adaptMesh();
          if (!last_.mesh_changed) break;
          add(tissue_->solveStatic());
        }
    }
  } catch (const NumericalError& e) {
    throw NumericalError(k, std::string(e.what()) + " (step " + std::to_string(k) + ")");
  }
  step_ = k;
  checkState();
  // Estimate, mark, refine / coarsen on the state just reached; the next step runs on the
  // new mesh. (The estimate of this step stays available to outputs when nothing changed.)
  // Contact events (first touch, puncture, a new or released constraint point) change the
  // load abruptly and locally: the mesh adapts at once rather than up to every_steps later.
  if (adaptation_ && (scene_.solver.mode == SolverSettings::Mode::Dynamic || interaction_)) {
    long signature = 0, states = 0;
    if (interaction_)
      for (int n = 0; n < numNeedles(); ++n) {
        signature = signature * 1000003 + interaction_->activePoints(n) * 8 + static_cast<int>(interaction_->state(n));
        states = states * 8 + static_cast<int>(interaction_->state(n));
      }
    // A deferred mesh change switches at its step, at this step boundary. A pass due while
    // one is being built, or at the switch, waits for the first step on the new mesh: its
    // estimate must be of a state computed there, not of one carried over.
    // A background pass's decision is taken up at its step: a change becomes the deferred
    // change a pass on this thread would have started, with the same switch step. A pass that
    // falls due before it, at a needle's touch or puncture, takes it up at once (waiting for
    // it if need be): the mesh must follow the puncture without delay (deferred to the
    // decision's step, the adaptive phantom's probes moved by 3.4 % of their largest
    // displacement from those of passes on the stepping thread). A pass due at a new or
    // released constraint point starts at the decision's step, after it: waiting there and
    // then for the background thread (a new shaft point a step after the regular pass) made
    // the adaptive phantom's slowest steps, 1-2.7 ms against a median of 0.3.
    bool switched = false;
    if (pending_pass_ && step_ >= pending_pass_->take_step) takePass();
    if (pending_rebuild_ && step_ >= pending_rebuild_->switch_step) {
      finishRebuild();
      switched = true;
    }
    const bool was_due = pass_due_;
    pass_due_ = pass_due_ || (step_ - step_base_) % every_steps_ == 0 || signature != contact_signature_;
    if (pass_due_ && pending_pass_ && states != contact_states_) takePass();
    if (pass_due_ && !was_due && pending_pass_) ++passes_after_decision_;
    if (pass_due_ && !pending_pass_ && !pending_rebuild_ && !switched) {
      pass_due_ = false;
      adaptMesh(scene_.solver.mode == SolverSettings::Mode::Dynamic);
    }
    contact_signature_ = signature;
    contact_states_ = states;
  }
  return last_;
}

}  // namespace needle_sim
