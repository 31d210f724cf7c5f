#pragma once
// A scene brought to life: builds the bodies from a validated Scene, embeds the probes and
// targets, runs the brain-shift pre-step, and advances time step by step (doc/method.md).
// The scene is kept as it was given; what changes at run time (the time step of a
// prediction, targets added by set_target) is the simulation's own state. The
// command-line tool and the ROS node are thin drivers around this class; what they report
// comes from observables.hpp.
#include <future>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include "needle_sim/adapt/goal_estimator.hpp"
#include "needle_sim/adapt/mesh_adaptation.hpp"
#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/contact/needle_tissue_interaction.hpp"
#include "needle_sim/fem/embedded_point.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/brain/brain_shift.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/needle/trajectory_replan.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& tissue);

class Simulation {
 public:
  // BLAS threads while a scene with a brain shift loads (its pre-step and the first step's
  // factor, on grids of 10,000 DOFs or more), process-wide: a one-off before any step, whose
  // large factorisations gain from every core; the steps then run with the count set before
  // (setBlasThreads). 0 (the default): no change. The tool and the node set it from
  // --setup-threads and ~setup_threads.
  static void setSetupThreads(int n);
  static int setupThreads();
  struct Options {
    // The goal-oriented estimates of the targets' displacement errors will be asked for
    // (targetErrors): the brain shift's own is then kept at the end of its pre-step.
    // (Implied by goal-oriented adaptivity.)
    bool target_errors = false;
  };
  // Throws InputError for scene content that only shows once the mesh exists (a probe
  // outside the tissue, a region selecting no node).
  explicit Simulation(const Scene& scene) : Simulation(scene, Options{}) {}
  Simulation(const Scene& scene, const Options& options);
  // A deep copy of the whole state (bodies and their factors, constraints and insertion
  // states, the adaptive mesh and its hysteresis, targets, loads, time): stepping the copy
  // leaves this one alone and gives, step for step, what this one would. A prediction
  // (predictInsertion) runs on one.
  Simulation(const Simulation& other);
  Simulation& operator=(const Simulation&) = delete;
  ~Simulation();

  // Steps with dt from now on (a prediction may step coarser than the live run). The
  // adaptation keeps its period in steps, counted from now (its share of the cost stays
  // what the scene chose; contact events still adapt at once). Throws
  // std::invalid_argument for a non-positive or non-finite dt.
  void setTimeStep(double dt);

  // Advances one time step (dynamic) or one quasi-static load step (static). Throws
  // NumericalError carrying the step index on NaN/Inf, divergence or solver failure.
  const StepStats& step();

  // The scene as it was given (never changed by the simulation).
  const Scene& scene() const { return scene_; }
  double dt() const { return dt_; }          // the time step now (setTimeStep)
  long stepIndex() const { return step_; }  // steps done
  double time() const { return time_base_ + (step_ - step_base_) * dt_; }
  bool hasTissue() const { return tissue_ != nullptr; }
  const TissueBody& tissue() const { return *tissue_; }
  TissueBody& tissue() { return *tissue_; }  // (tests: prescribed fields, states)
  // The needle-tissue interaction, or nullptr when the scene has none.
  const NeedleTissueInteraction* interaction() const { return interaction_.get(); }
  int numNeedles() const { return static_cast<int>(needles_.size()); }
  const NeedleBody& needle(int i) const { return *needles_[i]; }
  NeedleBody& needle(int i) { return *needles_[i]; }
  // All DOFs of all bodies.
  int numDofs() const;
  int numElements() const;
  double kineticEnergy() const;
  double elasticEnergy() const;
  const StepStats& lastStats() const { return last_; }

  // Adaptivity (nullptr without an `adaptivity` section).
  const MeshAdaptation* adaptation() const { return adaptation_.get(); }
  // Refinement level per tissue element (all 0 without adaptivity), of the mesh in use.
  std::vector<int> elementLevels() const;
  // Active elements per level 0..max_level and hanging nodes of the mesh in use (a deferred
  // mesh change is not in use until its switch).
  std::vector<int> elementsPerLevel() const;
  int hangingNodes() const { return hanging_nodes_; }
  // A mesh change decided and being built in the background (adaptivity.rebuild_delay).
  bool rebuildPending() const { return pending_rebuild_ != nullptr; }
  // Deferred mesh changes so far, and those whose switch had to wait for the build.
  long deferredRebuilds() const { return deferred_rebuilds_; }
  long rebuildWaits() const { return rebuild_waits_; }
  // An adaptation pass under way on a background thread (adaptivity.estimate_delay); passes
  // made so, and those whose decision had to be waited for when it was taken up.
  bool passPending() const { return pending_pass_ != nullptr; }
  long backgroundPasses() const { return background_passes_; }
  long passWaits() const { return pass_waits_; }
  // Passes that fell due at a new or released constraint point while a decision was still to
  // be taken up, and started at its step instead.
  long passesAfterDecision() const { return passes_after_decision_; }
  // Tests: every background mesh-change build, and every background pass's decision, takes at
  // least this long (late background work).
  static void setRebuildDelayForTesting(double ms);
  // SPR estimate of the current state; computed on first use after each step (adaptive
  // runs compute it anyway and share it).
  const ErrorEstimate& errorEstimate() const;
  // The state the estimate measures the change from (the shifted brain), or nullptr.
  const VecX* estimateReference() const { return reference_.size() ? &reference_ : nullptr; }
  // The last estimate computed (by the adaptation or errorEstimate()), or nullptr.
  const ErrorEstimate* lastEstimate() const { return estimate_ever_ ? &estimate_ : nullptr; }
  // The estimate of the current state if one was computed since the last step, or nullptr.
  const ErrorEstimate* currentEstimate() const { return estimate_step_ == step_ ? &estimate_ : nullptr; }
  // Goal-oriented estimates of the targets' displacement errors (goal_estimator.hpp), one
  // per target in order, for the current state: computed on first use after each step
  // (one 3-column dual solve with the current factor and three SPR recoveries per target).
  // After a brain shift, the estimate of the shift itself (kept from the end of the
  // pre-step) is added: errors add up, so do their bounds.
  const std::vector<TargetError>& targetErrors() const;
  const TargetError& targetError(int i) const;  // one of them (the same cache)
  // The last ones computed, or nullptr.
  const std::vector<TargetError>* lastTargetErrors() const { return errors_ever_ ? &target_errors_ : nullptr; }
  long lastTargetErrorStep() const { return last_error_step_; }
  // Radius of target i's regularised point [m].
  double qoiRadius(int i) const;
  // Refines the given tissue elements now (tests, scripted refinement), carrying the state
  // over; needs an adaptivity section.
  AdaptationResult refineElements(const std::vector<int>& elements);
  AdaptationResult coarsenElements(const std::vector<int>& elements);

  int numProbes() const { return static_cast<int>(probes_.size()); }
  const std::string& probeName(int i) const { return scene_.probes[i].name; }
  Vec3 probeDisplacement(int i) const;

  // Targets: material points tracked from the planning (rest) position.
  int numTargets() const { return static_cast<int>(targets_.size()); }
  const std::string& targetName(int i) const { return targets_[i].name; }
  Vec3 targetRest(int i) const { return targets_[i].planned; }
  Vec3 targetPosition(int i) const;
  // Position at step 0 (after the brain shift, if any).
  const Vec3& targetStart(int i) const { return target_start_[i]; }
  Vec3 targetVelocity(int i) const;
  int findTarget(const std::string& name) const;
  // Adds a target at a planning (rest) position, or moves the one of this name there; its
  // start position is where that material point is now. Returns its index. Throws
  // InputError (key "set_target") for an empty name or a point outside the tissue, and
  // changes nothing then.
  int setTarget(const std::string& name, const Vec3& point);

  // Immersed geometry (nullptr for box / block tissue): the grid and the organ surface
  // embedded in the current mesh.
  const ImmersedGrid* immersedGrid() const { return immersed_.get(); }
  const EmbeddedSurface* organSurface() const { return organ_.get(); }
  // The brain-shift pre-step's outcome (done == false without a brain_shift section).
  const BrainShiftResult& brainShift() const { return shift_result_; }
  // The needles' trajectories re-aimed after the shift (brain_shift.replan), one per needle
  // in order; empty without re-planning.
  const std::vector<TrajectoryReplan>& replans() const { return replans_; }

  // The material point at rest position p; throws InputError(file, key) naming `what` when
  // it lies outside the tissue (or the organ surface).
  EmbeddedPoint embedPoint(const PointLocator& locator, const Vec3& p, const std::string& file,
                           const std::string& key, const std::string& what) const;

 private:
  void checkState() const;
  // defer: a change may be built in the background (dynamic steps with a rebuild_delay).
  void adaptMesh(bool defer = false);
  // One estimate + mark + refine/coarsen pass with the scene's estimator (spr or goal).
  AdaptationResult adaptationPass();
  // The estimators bound to the current tissue body were made for another one.
  void forgetEstimates();
  // After the adaptation changed the mesh: new tissue body with the state carried over,
  // probes and constraint points re-embedded; without persistent_loads (during the
  // pre-step) the brain-shift loads are left out and the velocities zeroed.
  void rebuildTissue(bool persistent_loads = true);
  // A deferred mesh change (adaptivity.rebuild_delay): the new body built on a background
  // thread from this step's state, switched to rebuildLagSteps() later (finishRebuild, also
  // before any other adaptation pass).
  void startRebuild();
  void finishRebuild();
  // An adaptation pass on a background thread (adaptivity.estimate_delay): startPass copies
  // this step's state and starts it; takePass takes its decision up (waiting for it if need
  // be) at its step, or sooner when another pass falls due: a change becomes a deferred
  // rebuild (the background thread goes on to build its body) switched to at the same step
  // as a change decided on this thread. estimateLagSteps: estimate_delay in steps (0: none).
  void startPass();
  void takePass();
  long estimateLagSteps() const;
  // Waits for a background pass (its decision; with build, its body too): the estimator and
  // the adaptive forest are the pass's until then.
  void waitForPass(bool build) const;
  using HangingNodes = std::vector<std::vector<std::pair<int, double>>>;
  struct PreparedTissue;
  // A changed mesh's body, from any thread (values it owns; the scene and the frozen brain
  // shift read only): factor, compliance columns of the elements holding `points`, loads,
  // organ embedding, SPR fits.
  static std::shared_ptr<PreparedTissue> prepareTissue(const Scene& scene, double h, const BrainShift* shift,
                                                       double load_scale, HexMesh mesh, HangingNodes hanging,
                                                       const VecX& x, const VecX& v, const std::vector<Vec3>& points);
  // A copy of a prepared body for a copy of the simulation (its own lookups on its mesh).
  static std::shared_ptr<PreparedTissue> copyPrepared(const PreparedTissue& p);
  // The levels and hanging nodes of the adaptive mesh now in use.
  void noteActiveMesh();
  // rebuild_delay in steps of the current dt (0: synchronous).
  long rebuildLagSteps() const;
  // The brain-shift pre-step, with its solve/adapt passes on an adaptive mesh.
  void preStep();
  // brain_shift.coarse_start: solves the shift roughly on the grid one level coarser and
  // puts its state, interpolated, on the tissue; returns the pass's counts and its load scale
  // (coarse_dofs 0 when the scene does not call for it).
  BrainShiftResult coarseShiftStart(int target);
  // Re-aims every needle at the brain-shift target's shifted position (brain_shift.replan).
  void replanNeedles();
  static constexpr int kMaxShiftPasses = 6;
  // The skull support springs of the brain shift on the current mesh (support: on any body,
  // from any thread).
  void applySupport();
  static void support(const BrainShift* shift, TissueBody& body, const EmbeddedSurface* organ);
  void embedProbes();
  void embedTargets();
  void embedProbes(const PointLocator& locator);
  void embedTargets(const PointLocator& locator);
  // Volume fractions of the active mesh's elements (immersed geometry), cached per cell.
  void setFractions(HexMesh& mesh, const std::vector<int>& cells);
  // Loads that outlive a mesh change: the brain shift's gravity and skull reactions, and the
  // skull's support springs (applyPersistentLoads: on the tissue in use; persistentLoads: on
  // a body being built, from any thread: it reads the frozen brain-shift state only).
  void applyPersistentLoads();
  static void persistentLoads(const BrainShift* shift, double load_scale, TissueBody& body, const EmbeddedSurface* organ);

  const Scene scene_;
  // Run-time state.
  struct Target {
    std::string name;
    Vec3 planned;         // the planning (rest) position
    EmbeddedPoint point;  // embedded in the current mesh
    std::string key;      // where it came from (scene key, or "set_target")
    std::shared_ptr<const TriangleMesh> surface;  // a target given as a surface (centroid)
  };
  double dt_;
  std::unique_ptr<TissueBody> tissue_;
  // The body a deferred switch replaced: freeing it (its factor, matrices and model) took
  // 0.1-0.7 ms, most of a switch step on the phantom; the next background pass or build
  // frees it (startPass, startRebuild).
  std::unique_ptr<TissueBody> retired_tissue_;
  std::vector<std::unique_ptr<NeedleBody>> needles_;
  std::unique_ptr<NeedleTissueInteraction> interaction_;
  std::vector<EmbeddedPoint> probes_;
  std::vector<Target> targets_;
  std::vector<Vec3> target_start_;
  std::shared_ptr<const ImmersedGrid> immersed_;  // never changes: copies share it
  std::unordered_map<int, double> cell_fraction_;  // forest cell -> inside fraction (not floored)
  std::unique_ptr<EmbeddedSurface> organ_;
  std::unique_ptr<BrainShift> shift_;
  BrainShiftResult shift_result_;
  std::vector<TrajectoryReplan> replans_;
  VecX reference_;  // the shifted state (current mesh): the estimate's reference, or empty
  std::unique_ptr<MeshAdaptation> adaptation_;
  struct PreparedTissue {
    std::unique_ptr<TissueBody> tissue;  // with the brain shift's loads and support applied
    std::unique_ptr<EmbeddedSurface> organ;
    std::unique_ptr<SprEstimator> estimator;  // its per-mesh patch fits made
    // The mesh's lookups, so the switch only re-embeds: the probes' and targets' locator,
    // and the interaction's (with an interaction in the scene).
    std::unique_ptr<PointLocator> locator;
    TissueBinding binding;
  };
  struct PendingRebuild {
    std::shared_future<std::shared_ptr<PreparedTissue>> job;
    long switch_step = 0;
    std::vector<int> levels;
    int hanging = 0;
  };
  std::unique_ptr<PendingRebuild> pending_rebuild_;
  struct PassDecision {
    AdaptationResult result;
    ErrorEstimate estimate;        // of the pass's step
    std::vector<int> levels;       // of the new mesh, when it changed
    int hanging = 0;
    double estimate_ms = 0, mark_refine_ms = 0;  // on the background thread
  };
  struct PendingPass {
    long step = 0;         // whose state it estimates
    long take_step = 0;    // its decision is taken up here at the latest
    long switch_step = 0;  // a change is switched to here (as if decided at `step`)
    std::shared_future<std::shared_ptr<const PassDecision>> decision;
    std::shared_future<std::shared_ptr<PreparedTissue>> build;  // null after no change
  };
  std::unique_ptr<PendingPass> pending_pass_;
  std::vector<int> levels_;  // of the mesh in use
  int hanging_nodes_ = 0;
  long deferred_rebuilds_ = 0, rebuild_waits_ = 0;
  long background_passes_ = 0, pass_waits_ = 0, passes_after_decision_ = 0;
  mutable std::unique_ptr<SprEstimator> estimator_;  // bound to the current tissue body
  mutable ErrorEstimate estimate_;
  mutable long estimate_step_ = -1;
  mutable bool estimate_ever_ = false;
  Options options_;
  mutable std::vector<TargetQoi> qois_;  // per target, on the current mesh (empty: to be made)
  mutable std::vector<Eigen::MatrixXd> duals_;  // per target, the last duals on this mesh (CG's initial guess)
  mutable std::vector<TargetError> target_errors_;
  mutable long target_errors_step_ = -1;
  mutable bool errors_ever_ = false;
  mutable long last_error_step_ = -1;
  mutable std::vector<long> target_error_steps_;  // per target: the step its estimate is of
  VecX shifted_;  // the brain-shifted state (the goal estimate's reference; empty: none)
  mutable ErrorEstimate goal_primal_;  // the primal estimate against shifted_ (uniform meshes)
  mutable long goal_primal_step_ = -1;
  std::vector<TargetError> shift_errors_;  // the brain shift's, per target (empty: none)
  double qoi_radius_ = 0;                   // default radius: half the finest element's edge
  std::vector<int> goal_targets_;          // goal-oriented adaptivity: the targets it controls
  long contact_signature_ = 0;  // constraint counts and states at the last step
  long contact_states_ = 0;     // the needles' states (touch, puncture) at the last step
  bool pass_due_ = false;       // an adaptation pass waits for a deferred mesh change
  long step_ = 0;
  long step_base_ = 0;     // time() = time_base_ + (step_ - step_base_) dt, so that dt may change
  double time_base_ = 0;
  int every_steps_ = 1;    // adaptation period (steps since step_base_)
  StepStats last_;
  double diag_ = 1;
};

}  // namespace needle_sim
