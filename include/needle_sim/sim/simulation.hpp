#pragma once
// A scene brought to life (doc/method.md): the façade that wires the simulation's parts and
// steps them. The parts, each in its own files:
//   AdaptiveTissue        the tissue body on the mesh in use and its mesh changes
//   AdaptationPasses      when and where estimate-mark-refine passes run (background work)
//   TrackedPoints         probes and targets, re-embedded at every mesh change
//   EnergyErrorEstimator  the SPR estimate; TargetErrorEstimator, the targets' error bounds
//   coupledStep           one step of tissue, needles and their constraints
//   runBrainShiftPreStep  the brain shift (brain/), before the first step
// The scene is kept as it was given; what changes at run time (the time step of a
// prediction, targets added by setTarget) is the simulation's own state. The command-line
// tool and the ROS node are thin drivers around this class; what they report comes from
// observables.hpp.
#include <memory>
#include <string>
#include <vector>

#include "needle_sim/adapt/error_estimator.hpp"
#include "needle_sim/adapt/goal_estimator.hpp"
#include "needle_sim/adapt/mesh_adaptation.hpp"
#include "needle_sim/brain/brain_shift.hpp"
#include "needle_sim/contact/needle_tissue_interaction.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/needle/trajectory_replan.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/sim/adaptation_passes.hpp"
#include "needle_sim/sim/adaptive_tissue.hpp"
#include "needle_sim/sim/target_error_estimator.hpp"
#include "needle_sim/sim/tracked_points.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

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
  const TissueBody& tissue() const { return tissue_->body(); }
  TissueBody& tissue() { return tissue_->body(); }  // (tests: prescribed fields, states)
  // The needle-tissue interaction, or nullptr when the scene has none.
  const NeedleTissueInteraction* interaction() const { return interaction_.get(); }
  // Scene values the live simulation can take during a run, from its next step (an estimate
  // from measurements adopted: calibration/parameter_adoption.hpp): the tissue's Young's
  // modulus (tissue.material.young: AdaptiveTissue::setStiffnessScale) and the interaction's
  // cutting_force, puncture_force, friction and grip_pressure, by their scene keys. scene()
  // keeps the values it was given. adopt throws InputError for another key, a scene without
  // the part it names, or a value outside the key's declared range.
  static bool adoptable(const std::string& key);
  void adopt(const std::string& key, double value);
  double valueInUse(const std::string& key) const;  // an adoptable key's value now
  int numNeedles() const { return static_cast<int>(needles_.size()); }
  const NeedleBody& needle(int i) const { return *needles_[i]; }
  NeedleBody& needle(int i) { return *needles_[i]; }
  // The needle of this name, or -1.
  int findNeedle(const std::string& name) const;
  // All DOFs and elements of all bodies; their energies.
  int numDofs() const;
  int numElements() const;
  double kineticEnergy() const;
  double elasticEnergy() const;
  const StepStats& lastStats() const { return last_; }

  // Adaptivity (nullptr without an `adaptivity` section).
  const MeshAdaptation* adaptation() const { return tissue_ ? tissue_->adaptationView() : nullptr; }
  // Refinement level per tissue element (all 0 without adaptivity), of the mesh in use.
  std::vector<int> elementLevels() const;
  // Active elements per level 0..max_level and hanging nodes of the mesh in use (a deferred
  // mesh change is not in use until its switch).
  std::vector<int> elementsPerLevel() const;
  int hangingNodes() const { return tissue_ ? tissue_->numHanging() : 0; }
  // Background work: a mesh change being built, a pass under way, and the counts so far.
  bool rebuildPending() const { return passes_ && passes_->rebuildPending(); }
  bool passPending() const { return passes_ && passes_->passPending(); }
  // Background work still under way that a copy of this simulation would wait for (a factor
  // refresh, a mesh change's build, a pass): a copy taken on the stepping thread of a live
  // loop waits for none (the node's target-error estimates).
  bool backgroundWorkRunning() const {
    return (tissue_ && tissue().factorRefreshRunning()) || (passes_ && passes_->working());
  }
  AdaptationCounters adaptationCounters() const { return passes_ ? passes_->counters() : AdaptationCounters{}; }
  // SPR estimate of the current state; computed on first use after each step (adaptive
  // runs compute it anyway and share it).
  const ErrorEstimate& errorEstimate() const;
  // The state the estimate measures the change from (the shifted brain), or nullptr.
  const VecX* estimateReference() const { return energy_ ? energy_->reference() : nullptr; }
  // The last estimate computed (by the adaptation or errorEstimate()), or nullptr.
  const ErrorEstimate* lastEstimate() const { return energy_ ? energy_->last() : nullptr; }
  // The estimate of the current state if one was computed since the last step, or nullptr.
  const ErrorEstimate* currentEstimate() const { return energy_ ? energy_->current() : nullptr; }
  // Goal-oriented estimates of the targets' displacement errors (TargetErrorEstimator), one
  // per target in order, for the current state: computed on first use after each step.
  // After a brain shift, the estimate of the shift itself is added.
  const std::vector<TargetError>& targetErrors() const;
  const TargetError& targetError(int i) const;  // one of them (the same cache)
  // The last ones computed, or nullptr; the step they are of.
  const std::vector<TargetError>* lastTargetErrors() const { return target_errors_ ? target_errors_->last() : nullptr; }
  long lastTargetErrorStep() const { return target_errors_ ? target_errors_->lastStep() : -1; }
  // Radius of target i's regularised point [m].
  double qoiRadius(int i) const { return target_errors_->radius(i, *points_); }
  // Refines (coarsens) the given tissue elements now (tests, scripted refinement), carrying
  // the state over; needs an adaptivity section.
  AdaptationResult refineElements(const std::vector<int>& elements);
  AdaptationResult coarsenElements(const std::vector<int>& elements);

  int numProbes() const { return points_ ? points_->numProbes() : 0; }
  const std::string& probeName(int i) const { return points_->probeName(i); }
  Vec3 probeDisplacement(int i) const;

  // Targets: material points tracked from the planning (rest) position.
  int numTargets() const { return points_ ? points_->numTargets() : 0; }
  const std::string& targetName(int i) const { return points_->target(i).name; }
  Vec3 targetRest(int i) const { return points_->target(i).planned; }
  Vec3 targetPosition(int i) const;
  // Position at step 0 (after the brain shift, if any).
  const Vec3& targetStart(int i) const { return target_start_[i]; }
  Vec3 targetVelocity(int i) const;
  int findTarget(const std::string& name) const { return points_ ? points_->findTarget(name) : -1; }
  // Adds a target at a planning (rest) position, or moves the one of this name there; its
  // start position is where that material point is now. Returns its index. Throws
  // InputError (key "set_target") for an empty name or a point outside the tissue, and
  // changes nothing then.
  int setTarget(const std::string& name, const Vec3& point);
  // The material point at rest position p of the mesh in use; throws InputError(key)
  // naming `what` when it lies outside the tissue (or the organ surface).
  EmbeddedPoint embedPoint(const Vec3& p, const std::string& key, const std::string& what) const;

  // Immersed geometry (nullptr for box / block tissue): the grid and the organ surface
  // embedded in the current mesh.
  const ImmersedGrid* immersedGrid() const { return tissue_ ? tissue_->immersed().get() : nullptr; }
  const EmbeddedSurface* organSurface() const { return tissue_ ? tissue_->organ() : nullptr; }
  // The brain-shift pre-step's outcome (done == false without a brain_shift section).
  const BrainShiftResult& brainShift() const { return shift_result_; }
  // The needles' trajectories re-aimed after the shift (brain_shift.replan), one per needle
  // in order; empty without re-planning.
  const std::vector<TrajectoryReplan>& replans() const { return replans_; }

  // Tests: every background mesh-change build, and every background pass's decision, takes at
  // least this long (late background work).
  static void setRebuildDelayForTesting(double ms) { AdaptationPasses::setDelayForTesting(ms); }

 private:
  class ShiftTissue;
  void checkState() const;
  StepClock clock() const { return {step_, step_base_, dt_}; }
  TargetErrorState errorState() const;
  ErrorEstimator& markingEstimator() { return goal_ ? *goal_ : static_cast<ErrorEstimator&>(*energy_); }
  // The parts that estimate and adapt, for this body (constructor and copy).
  void makeEstimation(const Simulation* copy_of);
  // The mesh changed (AdaptiveTissue's switch): its dependents re-bound.
  void onMeshSwitch(AdaptiveTissue::Switch& s);
  // The estimates bound to the tissue body were made for another state or mesh.
  void forgetEstimates();
  std::vector<Vec3> constraintPoints() const;
  // AdaptivitySettings::lookahead: points on each needle's path ahead of its tip (rest frame).
  std::vector<Vec3> aheadPoints() const;
  double finest_edge_ = 0;  // the finest element's edge the adaptivity allows [m]
  // The brain-shift pre-step and what the insertion keeps of it; the re-aimed needles.
  void preStep();
  void replanNeedles();
  void makeInteraction(const NeedleTissueInteraction* copy_of);
  AdaptationResult scriptedChange(const std::vector<int>& elements,
                                  AdaptationResult (MeshAdaptation::*change)(const std::vector<int>&));

  const Scene scene_;
  Options options_;
  double dt_;
  long step_ = 0;
  long step_base_ = 0;     // time() = time_base_ + (step_ - step_base_) dt, so that dt may change
  double time_base_ = 0;
  StepStats last_;
  double diag_ = 1;        // the tissue's bounding-box diagonal (the divergence check's scale)
  std::vector<std::unique_ptr<NeedleBody>> needles_;
  std::unique_ptr<AdaptiveTissue> tissue_;
  std::unique_ptr<TrackedPoints> points_;
  std::vector<Vec3> target_start_;
  std::unique_ptr<NeedleTissueInteraction> interaction_;
  std::unique_ptr<BrainShift> shift_;
  BrainShiftResult shift_result_;
  std::vector<TrajectoryReplan> replans_;
  std::vector<int> goal_targets_;  // goal-oriented adaptivity: the targets it controls
  std::unique_ptr<EnergyErrorEstimator> energy_;
  std::unique_ptr<TargetErrorEstimator> target_errors_;
  std::unique_ptr<GoalErrorEstimator> goal_;  // goal-oriented marking, or nullptr
  // Last: destroyed first, waiting for background work that reads the parts above.
  std::unique_ptr<AdaptationPasses> passes_;
};

}  // namespace needle_sim
