#include "needle_sim/sim/simulation.hpp"

#include <atomic>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_sim/brain/brain_shift_prestep.hpp"
#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/scene/scene_check.hpp"
#include "needle_sim/sim/coupled_step.hpp"

namespace needle_sim {

namespace {
std::atomic<int> g_setup_threads{0};
}  // namespace

void Simulation::setSetupThreads(int n) { g_setup_threads = std::max(n, 0); }
int Simulation::setupThreads() { return g_setup_threads; }

// The tissue as the brain-shift pre-step sees it: its passes re-mesh without the shift's
// loads (the pre-step applies them afresh on each mesh).
class Simulation::ShiftTissue : public PreStepTissue {
 public:
  explicit ShiftTissue(Simulation& sim) : sim_(sim) {}
  TissueBody& body() override { return sim_.tissue_->body(); }
  const EmbeddedSurface* organ() const override { return sim_.tissue_->organ(); }
  const EmbeddedPoint* target() const override {
    const std::string& name = sim_.scene_.brain_shift->target;
    const int t = name.empty() ? -1 : sim_.findTarget(name);
    return t >= 0 ? &sim_.points_->target(t).point : nullptr;
  }
  bool adaptive() const override { return sim_.tissue_->adaptive(); }
  bool adapt() override {
    const AdaptationResult a = sim_.passes_->pass();
    if (a.changed) sim_.tissue_->rebuild(false);
    return a.changed;
  }
  void checkState() const override { sim_.checkState(); }

 private:
  Simulation& sim_;
};

Simulation::Simulation(const Scene& scene, const Options& options) : scene_(scene), options_(options), dt_(scene.dt) {
  checkScene(scene_);  // a scene built in code passes the loader's checks too
  for (const auto& n : scene.needles) needles_.push_back(std::make_unique<NeedleBody>(n, scene.solver));
  if (!scene.has_tissue) return;
  tissue_ = std::make_unique<AdaptiveTissue>(scene_);
  const HexMesh& mesh = tissue_->body().mesh();
  diag_ = (mesh.boundsMax() - mesh.boundsMin()).norm();
  points_ = std::make_unique<TrackedPoints>(scene_, tissue_->immersed());
  points_->embed(PointLocator(mesh));
  if (scene.adaptivity && scene.adaptivity->estimator == AdaptivitySettings::Estimator::Goal) {
    options_.target_errors = true;
    for (const auto& name : scene.adaptivity->goal_targets) goal_targets_.push_back(findTarget(name));
  }
  makeEstimation(nullptr);
  // A needle must start outside the tissue: puncture happens on the surface.
  const PointLocator locator(mesh);
  for (size_t n = 0; n < needles_.size(); ++n)
    for (int i = 0; i < needles_[n]->beam().numNodes(); ++i) {
      EmbeddedPoint ep;
      const Vec3& p = needles_[n]->state().p[i];
      const bool inside = tissue_->immersed() ? tissue_->immersed()->insideTest().inside(p) : locator.locate(p, ep);
      if (inside) {
        std::ostringstream m;
        m << "the needle starts inside the tissue (node " << i << " at (" << p.transpose()
          << ")); place its tip outside the tissue surface";
        throw InputError(scene.file, scene.needles[n].key + ".base.position", m.str());
      }
    }
  makeInteraction(nullptr);
  // The brain shift's static solves (and the first step's factor) may use more BLAS threads;
  // they pay off only for large factors (on 3,000 DOFs two threads gained nothing).
  constexpr int kSetupThreadsMinDofs = 10000;
  ScopedBlasThreads setup_threads(scene.brain_shift && mesh.numDofs() >= kSetupThreadsMinDofs ? setupThreads() : 0);
  if (scene.brain_shift) preStep();
  if (scene.brain_shift && scene.brain_shift->replan) replanNeedles();
  for (int i = 0; i < numTargets(); ++i) target_start_.push_back(targetPosition(i));
  // The first dynamic step's factor is part of loading the scene, as a mesh change's is part
  // of its background build: step 1 costs what any step does.
  if (scene.solver.mode == SolverSettings::Mode::Dynamic) tissue_->body().prepareForSteps(dt_, {});
  // So are the SPR patch fits of the first mesh (30 ms on the DBS mesh at the first pass).
  if (tissue_->adaptive()) energy_->spr();
}

// A background pass has finished with what is copied before anything is.
static const Scene& settledScene(const Simulation& o, const std::unique_ptr<AdaptationPasses>& passes) {
  if (passes) passes->settle(true);
  return o.scene();
}

Simulation::Simulation(const Simulation& o)
    : scene_(settledScene(o, o.passes_)),
      options_(o.options_),
      dt_(o.dt_),
      step_(o.step_),
      step_base_(o.step_base_),
      time_base_(o.time_base_),
      last_(o.last_),
      diag_(o.diag_),
      target_start_(o.target_start_),
      shift_result_(o.shift_result_),
      replans_(o.replans_),
      goal_targets_(o.goal_targets_) {
  for (const auto& n : o.needles_) needles_.push_back(std::make_unique<NeedleBody>(*n));
  if (!o.tissue_) return;
  tissue_ = std::make_unique<AdaptiveTissue>(*o.tissue_, scene_);
  points_ = std::make_unique<TrackedPoints>(*o.points_);
  if (o.shift_) {
    shift_ = std::make_unique<BrainShift>(*o.shift_);
    shift_->rebind(tissue_->organ());
  }
  if (o.tissue_->persistentShift())
    tissue_->setPersistentLoads(shift_.get(), shift_result_.load_scale, o.tissue_->loadsWithStiffness());
  makeEstimation(&o);
  makeInteraction(o.interaction_.get());
}

Simulation::~Simulation() { passes_.reset(); }  // background work reads the parts: it stops first

void Simulation::makeEstimation(const Simulation* o) {
  // The regularised point of the goal estimate: a ball of half the finest element's edge.
  const auto X = tissue_->body().mesh().elementCorners(0);
  const double edge = (X.colwise().maxCoeff() - X.colwise().minCoeff()).minCoeff();
  finest_edge_ = edge / std::pow(2.0, scene_.adaptivity ? scene_.adaptivity->max_level : 0);
  const double radius = 0.5 * finest_edge_;
  if (o) {
    energy_ = std::make_unique<EnergyErrorEstimator>(*o->energy_, &tissue_->body(), &tissue_->reference());
    target_errors_ = std::make_unique<TargetErrorEstimator>(*o->target_errors_);
  } else {
    energy_ = std::make_unique<EnergyErrorEstimator>(&tissue_->body(), &tissue_->reference());
    target_errors_ = std::make_unique<TargetErrorEstimator>(radius);
  }
  if (!goal_targets_.empty())
    goal_ = std::make_unique<GoalErrorEstimator>(
        *energy_, [this](int t) -> const TargetError& { return targetError(t); }, goal_targets_,
        scene_.adaptivity->goal_tolerance);
  auto points = [this] { return constraintPoints(); };
  if (o && o->passes_) {
    passes_ = std::make_unique<AdaptationPasses>(*o->passes_, *tissue_, *energy_, markingEstimator(), points);
  } else if (tissue_->adaptive()) {
    passes_ = std::make_unique<AdaptationPasses>(*scene_.adaptivity, *tissue_, *energy_, markingEstimator(),
                                                 !goal_targets_.empty(), points);
  }
  if (passes_ && scene_.adaptivity->lookahead > 0) passes_->setAhead([this] { return aheadPoints(); });
  if (passes_ && goal_)
    passes_->setGoalPasses(
        [this] {
          return std::make_shared<GoalPass>(*target_errors_, errorState(), goal_targets_, scene_.adaptivity->goal_tolerance);
        },
        [this](const GoalPass& g) { g.adoptInto(*target_errors_); });
  tissue_->setOnSwitch([this](AdaptiveTissue::Switch& s) { onMeshSwitch(s); });
}

void Simulation::makeInteraction(const NeedleTissueInteraction* o) {
  if (!scene_.interaction) return;
  std::vector<NeedleBody*> nd;
  for (auto& n : needles_) nd.push_back(n.get());
  if (o) interaction_ = std::make_unique<NeedleTissueInteraction>(*o, tissue_->body(), nd, tissue_->organ());
  else interaction_ = std::make_unique<NeedleTissueInteraction>(*scene_.interaction, tissue_->body(), nd, tissue_->organ());
}

std::vector<Vec3> Simulation::constraintPoints() const {
  std::vector<Vec3> points;
  if (interaction_) {
    for (const auto& c : interaction_->constraints()) points.push_back(c->tissue.rest);
    // A deferred mesh change's body gets the columns ahead of the needles too: a shaft point
    // laid or a tip entering an element just after the switch found none (DBS, 4-8 ms).
    if (scene_.solver.linear.columns_ahead)
      for (const Vec3& p : interaction_->pointsAhead()) points.push_back(p);
  }
  return points;
}

std::vector<Vec3> Simulation::aheadPoints() const {
  // The segment the tip will sweep within the lookahead by its base's commanded advance,
  // sampled at half the finest edge; it starts that advance (at least two finest edges)
  // behind the tip, since the material under an indenting tip sat behind it at rest. Each
  // sample also a quarter edge off the axis in four directions: an axis along element faces
  // or edges (the phantom's) has its elements on every side refined, not the one a point
  // on the boundary happens to be located in.
  std::vector<Vec3> points;
  const double t = time(), h = scene_.adaptivity->lookahead, step = 0.5 * finest_edge_;
  for (const auto& n : needles_) {
    const BasePose now = n->trajectory().pose(t), later = n->trajectory().pose(t + h);
    const double advance = (later.position - now.position).dot(now.direction);
    if (!(advance > 0)) continue;
    const Vec3 tip = n->tipPosition(), d = now.direction;
    const Vec3 u = d.unitOrthogonal(), v = d.cross(u);
    const double back = std::max(advance, 2 * finest_edge_), off = 0.25 * finest_edge_ / std::sqrt(2.0);
    for (double s = -back; s <= advance + step; s += step) {
      const Vec3 c = tip + s * d;
      points.push_back(c);
      for (const Vec3& w : {Vec3(u + v), Vec3(u - v), Vec3(v - u), Vec3(-u - v)}) points.push_back(c + off * w);
    }
  }
  return points;
}

void Simulation::onMeshSwitch(AdaptiveTissue::Switch& s) {
  energy_->rebind(&s.body, std::move(s.spr));
  target_errors_->forget();
  points_->embed(s.locator);
  if (interaction_) {
    if (s.binding) interaction_->rebind(tissue_->body(), std::move(*s.binding));
    else interaction_->rebind(tissue_->body(), s.organ);
  }
}

void Simulation::forgetEstimates() {
  energy_->rebind(&tissue_->body());
  target_errors_->forget();
}

void Simulation::setTimeStep(double dt) {
  if (!(dt > 0) || !std::isfinite(dt)) throw std::invalid_argument("time step must be positive and finite");
  time_base_ = time();
  step_base_ = step_;
  dt_ = dt;
}

void Simulation::preStep() {
  const auto t0 = steadyNow();
  const bool immersed = tissue_->immersed() != nullptr;
  const PreStepScene ps{*scene_.brain_shift, scene_.tissue, scene_.solver, scene_.file,
                        immersed ? scene_.tissue.geometry.surface : nullptr,
                        immersed ? &scene_.tissue.geometry.grid : nullptr};
  ShiftTissue host(*this);
  BrainShiftResult total = runBrainShiftPreStep(ps, host, shift_);
  const int t = scene_.brain_shift->target.empty() ? -1 : findTarget(scene_.brain_shift->target);
  // The shift's own error on the targets, before the estimate's reference becomes the
  // shifted state (the insertion's estimates add it).
  if (options_.target_errors && numTargets() > 0) {
    std::vector<TargetError> errors = targetErrors();
    // target_shift scales the load to prescribe the length of that target's shift: the scale
    // carries the mesh's error along the shift, and every target's error is that of the
    // scaled problem (doc/method.md "Error on target motion"); for that target, its error
    // across the shift.
    if (t >= 0 && scene_.brain_shift->target_shift && total.target_displacement.norm() > 0) {
      const Vec3 d = total.target_displacement.normalized();
      for (int i = 0; i < static_cast<int>(errors.size()); ++i)
        errors[i] = target_errors_->underPrescribedShift(i, t, errorState(), d);
    }
    target_errors_->setShiftErrors(std::move(errors));
    tissue_->shifted() = tissue_->body().positions();
    forgetEstimates();
  }
  shift_->applySupport(tissue_->body(), tissue_->organ());
  if (tissue_->adaptive()) {
    // From now on the mesh adapts to the insertion: the estimate measures the stress change
    // since the shift, and the shift's refinement stays.
    tissue_->adaptation()->keepCurrentRefinement();
    tissue_->reference() = tissue_->body().positions();
    forgetEstimates();
  }
  tissue_->setPersistentLoads(shift_.get(), total.load_scale, t >= 0 && scene_.brain_shift->target_shift);
  total.ms = msSince(t0);
  shift_result_ = total;
}

void Simulation::replanNeedles() {
  const int t = findTarget(scene_.brain_shift->target);
  const Vec3 shift = targetPosition(t) - targetRest(t);
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
  makeInteraction(nullptr);
}

void Simulation::checkState() const { checkBodies(tissue_ ? &tissue_->body() : nullptr, needles_, step_, diag_); }

const StepStats& Simulation::step() {
  const long k = step_ + 1;
  const bool dynamic = scene_.solver.mode == SolverSettings::Mode::Dynamic;
  try {
    last_ = coupledStep({tissue_ ? &tissue_->body() : nullptr, &needles_, interaction_.get()}, time(), dt_, dynamic);
    // A static load step on an adaptive mesh: solve, estimate, adapt and solve again on the
    // new mesh until it stays as it is (the state a step ends in is an equilibrium on the
    // mesh it is reported on).
    if (!interaction_ && !dynamic && passes_)
      for (int pass = 1; pass < kMaxStaticAdaptationPasses; ++pass) {
        last_.mesh_changed = false;
        passes_->adaptNow(clock(), false, last_);
        if (!last_.mesh_changed) break;
        last_.accumulate(tissue_->body().solveStatic());
      }
  } catch (const NumericalError& e) {
    throw NumericalError(k, std::string(e.what()) + " (step " + std::to_string(k) + ")");
  }
  step_ = k;
  if (energy_) energy_->reset();  // (the target errors are cached by step)
  checkState();
  // Estimate, mark, refine / coarsen on the state just reached; the next step runs on the
  // new mesh. Contact events (first touch, puncture, a new or released constraint point)
  // change the load abruptly and locally: the mesh adapts at once rather than up to
  // every_steps later.
  if (passes_ && (dynamic || interaction_)) {
    long signature = 0, states = 0;
    if (interaction_)
      for (int n = 0; n < numNeedles(); ++n) {
        signature = signature * 1000003 + interaction_->activePoints(n) * 8 + static_cast<int>(interaction_->state(n));
        states = states * 8 + static_cast<int>(interaction_->state(n));
      }
    passes_->afterStep(clock(), signature, states, dynamic, last_);
  }
  return last_;
}

AdaptationResult Simulation::refineElements(const std::vector<int>& elements) {
  return scriptedChange(elements, &MeshAdaptation::refineElements);
}

AdaptationResult Simulation::coarsenElements(const std::vector<int>& elements) {
  return scriptedChange(elements, &MeshAdaptation::coarsenElements);
}

AdaptationResult Simulation::scriptedChange(const std::vector<int>& elements,
                                            AdaptationResult (MeshAdaptation::*change)(const std::vector<int>&)) {
  if (!passes_) throw std::logic_error("refineElements/coarsenElements: the scene has no adaptivity section");
  passes_->flush(last_);
  const AdaptationResult r = (tissue_->adaptation()->*change)(elements);
  if (r.changed) tissue_->rebuild(true);
  return r;
}

const ErrorEstimate& Simulation::errorEstimate() const {
  if (passes_) passes_->settle();  // the fits are a background pass's until its decision
  return energy_->localErrors();
}

TargetErrorState Simulation::errorState() const {
  const VecX& shifted = tissue_->shifted();
  return {tissue_->body(), *energy_, shifted.size() ? &shifted : nullptr, *points_, step_};
}

const TargetError& Simulation::targetError(int i) const {
  if (passes_) passes_->settle();
  return target_errors_->of(i, errorState());
}

const std::vector<TargetError>& Simulation::targetErrors() const {
  if (passes_) passes_->settle();
  return target_errors_->all(errorState());
}

int Simulation::setTarget(const std::string& name, const Vec3& point) {
  if (name.empty()) throw InputError("", "set_target.name", "must not be empty");
  if (!tissue_) throw InputError("", "set_target", "the scene has no tissue");
  const int i = points_->setTarget(name, point, tissue_->body().mesh());
  if (i == static_cast<int>(target_start_.size())) target_start_.push_back(Vec3::Zero());
  target_errors_->targetsChanged();
  target_start_[i] = targetPosition(i);
  return i;
}

EmbeddedPoint Simulation::embedPoint(const Vec3& p, const std::string& key, const std::string& what) const {
  if (!tissue_) throw InputError("", key, "the scene has no tissue");
  return points_->embedPoint(PointLocator(tissue_->body().mesh()), p, "", key, what);
}

namespace {

// The adoptable keys and their fields (Simulation::adopt).
double* adoptableField(InteractionSettings& s, const std::string& key) {
  if (key == "interaction.cutting_force") return &s.cutting_force;
  if (key == "interaction.puncture_force") return &s.puncture_force;
  if (key == "interaction.friction") return &s.friction;
  if (key == "interaction.grip_pressure") return &s.grip_pressure;
  return nullptr;
}

const char* const kYoung = "tissue.material.young";

}  // namespace

bool Simulation::adoptable(const std::string& key) {
  InteractionSettings s;
  return key == kYoung || adoptableField(s, key) != nullptr;
}

void Simulation::adopt(const std::string& key, double value) {
  if (!adoptable(key))
    throw InputError("", key, "not a value the live simulation can take during a run (it can: tissue.material.young, "
                              "interaction.cutting_force, puncture_force, friction, grip_pressure)");
  if (key == kYoung) {
    if (!tissue_) throw InputError("", key, "the scene has no tissue");
    if (!(value > 0) || !std::isfinite(value)) throw InputError("", key, "the value " + Range::number(value) + " is not positive");
    // A factor on the scene's modulus: every element's stiffness (and, under a prescribed
    // brain shift, its load) scales with it from the next step.
    tissue_->setStiffnessScale(value / scene_.tissue.material.young);
    return;
  }
  if (!interaction_) throw InputError("", key, "the scene has no needle-tissue interaction");
  InteractionSettings s = interaction_->settings();
  const std::string name = key.substr(key.find('.') + 1);
  for (const ParameterDeclaration& d : InteractionSettings::parameters().declarations())
    if (d.key == name && !d.range.contains(value))
      throw InputError("", key, "the value " + Range::number(value) + " is outside " + d.range.text());
  *adoptableField(s, key) = value;
  interaction_->setValues(s);
}

double Simulation::valueInUse(const std::string& key) const {
  if (key == kYoung) return tissue_ ? scene_.tissue.material.young * tissue_->stiffnessScale() : std::numeric_limits<double>::quiet_NaN();
  if (!adoptable(key) || !interaction_) return std::numeric_limits<double>::quiet_NaN();
  InteractionSettings s = interaction_->settings();
  return *adoptableField(s, key);
}

int Simulation::findNeedle(const std::string& name) const {
  for (int i = 0; i < numNeedles(); ++i)
    if (needles_[i]->name() == name) return i;
  return -1;
}

Vec3 Simulation::probeDisplacement(int i) const {
  const EmbeddedPoint& ep = points_->probe(i);
  return ep.interpolate(tissue_->body().mesh(), tissue_->body().positions()) - ep.rest;
}

Vec3 Simulation::targetPosition(int i) const {
  return points_->target(i).point.interpolate(tissue_->body().mesh(), tissue_->body().positions());
}

Vec3 Simulation::targetVelocity(int i) const {
  return points_->target(i).point.interpolate(tissue_->body().mesh(), tissue_->body().velocities());
}

std::vector<int> Simulation::elementLevels() const {
  if (passes_) return tissue_->levels();
  return std::vector<int>(tissue_ ? tissue_->body().mesh().numElements() : 0, 0);
}

std::vector<int> Simulation::elementsPerLevel() const {
  const MeshAdaptation* a = adaptation();
  std::vector<int> n((a ? a->settings().max_level : 0) + 1, 0);
  if (!a) {
    n[0] = tissue_ ? tissue_->body().mesh().numElements() : 0;
    return n;
  }
  for (int l : tissue_->levels())
    if (l >= 0 && l < static_cast<int>(n.size())) ++n[l];
  return n;
}

int Simulation::numDofs() const {
  int n = tissue_ ? tissue_->body().mesh().numDofs() : 0;
  for (const auto& nd : needles_) n += nd->numDofs();
  return n;
}

int Simulation::numElements() const {
  int n = tissue_ ? tissue_->body().mesh().numElements() : 0;
  for (const auto& nd : needles_) n += nd->beam().numElements();
  return n;
}

double Simulation::kineticEnergy() const {
  double e = tissue_ ? tissue_->body().kineticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->kineticEnergy();
  return e;
}

double Simulation::elasticEnergy() const {
  double e = tissue_ ? tissue_->body().elasticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->elasticEnergy();
  return e;
}

}  // namespace needle_sim
