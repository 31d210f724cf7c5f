#pragma once
// The tissue body on the mesh in use, and its mesh changes (doc/method.md, "Refinement and
// coarsening"). A change the forest decided is prepared — a new body on the new mesh with the
// state carried over (MeshAdaptation::transfer), the brain shift's persistent loads, the
// organ surface and the point lookups, and for a change built in the background also its
// factor, compliance columns, SPR fits and the interaction's binding — and then switched to:
// the state of the switch's moment is carried once more, and the mesh's dependents (probes,
// targets, the interaction, the estimators) are re-bound through the switch callback (as
// deal.II's Triangulation signals its post-refinement listeners). A synchronous change is the
// same prepare and switch done at once, its factor made by the first step.
//
// Threading: prepare() may run on any thread (it reads the scene and the frozen brain shift
// only). From AdaptationPasses' lend() to the background pass's giveBack(), the forest and
// the volume fractions are the pass's: adaptation() throws std::logic_error on the stepping
// thread then, and the pass uses adaptationOfPass().
#include <atomic>
#include <functional>
#include <memory>
#include <unordered_map>
#include <vector>

#include "needle_sim/adapt/mesh_adaptation.hpp"
#include "needle_sim/adapt/spr_estimator.hpp"
#include "needle_sim/brain/brain_shift.hpp"
#include "needle_sim/contact/needle_tissue_interaction.hpp"
#include "needle_sim/geometry/embedded_surface.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/scene/scene.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& tissue);

class AdaptiveTissue {
 public:
  using HangingNodes = std::vector<std::vector<std::pair<int, double>>>;
  // A mesh the forest decided on: its volume fractions set, its hanging nodes and levels.
  struct MeshChange {
    HexMesh mesh;
    HangingNodes hanging;
    std::vector<int> levels;
    int num_hanging = 0;
  };
  // A changed mesh's body, made ready to switch to.
  struct Prepared {
    std::unique_ptr<TissueBody> body;  // with the brain shift's loads and support applied
    std::unique_ptr<EmbeddedSurface> organ;
    std::unique_ptr<PointLocator> locator;  // the probes' and targets' lookups (null: made at the switch)
    std::unique_ptr<SprEstimator> spr;      // built in the background: its patch fits
    TissueBinding binding;                  // built in the background: the interaction's lookups
    std::vector<int> levels;
    int num_hanging = 0;
    double stiffness_scale = 1;  // the one the body and its loads were made with
  };
  // What a switch hands to the mesh's dependents.
  struct Switch {
    const TissueBody& body;
    const EmbeddedSurface* organ;
    const PointLocator& locator;
    TissueBinding* binding;             // nullptr: the interaction makes its own
    std::unique_ptr<SprEstimator> spr;  // nullptr: made on first use
  };

  // Builds the scene's mesh (box, block or immersed grid; the adaptive forest's active mesh)
  // and the body on it. Throws InputError for an invalid mesh.
  explicit AdaptiveTissue(const Scene& scene);
  // A deep copy for a copy of the simulation (scene: the copy's); its dependents and its
  // persistent loads are set by the copy.
  AdaptiveTissue(const AdaptiveTissue& other, const Scene& scene);
  AdaptiveTissue(const AdaptiveTissue&) = delete;
  AdaptiveTissue& operator=(const AdaptiveTissue&) = delete;

  TissueBody& body() { return *body_; }
  const TissueBody& body() const { return *body_; }
  const EmbeddedSurface* organ() const { return organ_.get(); }
  const std::shared_ptr<const ImmersedGrid>& immersed() const { return immersed_; }
  bool adaptive() const { return adaptation_ != nullptr; }
  // The forest (nullptr without adaptivity), on the stepping thread.
  MeshAdaptation* adaptation();
  // Read-only view for reports (its settings never change; its active mesh is the pass's
  // while one is under way).
  const MeshAdaptation* adaptationView() const { return adaptation_.get(); }
  // The background pass's access while the forest is lent to it.
  MeshAdaptation& adaptationOfPass() { return *adaptation_; }
  void lend() { lent_ = true; }
  void giveBack() { lent_ = false; }

  // Levels per element and hanging nodes of the mesh in use.
  const std::vector<int>& levels() const { return levels_; }
  int numHanging() const { return hanging_; }
  // States carried to every new mesh: the SPR estimate's reference (the shifted brain, on an
  // adaptive mesh) and the goal estimate's (on a uniform one); empty: none.
  VecX& reference() { return reference_; }
  const VecX& reference() const { return reference_; }
  VecX& shifted() { return shifted_; }
  const VecX& shifted() const { return shifted_; }

  // From the end of the brain-shift pre-step: its loads outlive every mesh change.
  // with_stiffness: the shift's load (gravity at load_scale and the frozen skull reactions)
  // goes with the stiffness in use (brain_shift.target_shift: a measured shift, which a stiffer
  // brain reaches under a proportionally larger load, as the pre-step would have scaled it).
  void setPersistentLoads(const BrainShift* shift, double load_scale, bool with_stiffness) {
    shift_ = shift;
    load_scale_ = load_scale;
    loads_with_stiffness_ = with_stiffness;
  }
  bool loadsWithStiffness() const { return loads_with_stiffness_; }
  // Young's modulus adopted during a run, as a factor on the scene's: on the body in use (its
  // shift loads with it, see above) and on every body prepared from now on (stepping thread).
  void setStiffnessScale(double k);
  double stiffnessScale() const { return stiffness_scale_.load(std::memory_order_relaxed); }
  const BrainShift* persistentShift() const { return shift_; }
  void setOnSwitch(std::function<void(Switch&)> f) { on_switch_ = std::move(f); }

  // The forest's active mesh as a change (on the pass's thread while lent).
  MeshChange forestMesh(MeshAdaptation& forest);
  // The body on a changed mesh with the state x, v (on the new mesh); persistent_loads:
  // with the brain shift's loads (not during the pre-step); steps_h > 0: also the factor for
  // dynamic steps of that length and the compliance columns of the elements holding
  // `points`, the SPR fits and the interaction's binding (a change built in the
  // background). Any thread.
  std::shared_ptr<Prepared> prepare(MeshChange change, const VecX& x, const VecX& v, bool persistent_loads,
                                    double steps_h = 0, const std::vector<Vec3>& points = {}) const;
  // A copy of a prepared body (for a copy of the simulation; its lookups made at its switch).
  static std::shared_ptr<Prepared> copyPrepared(const Prepared& p);
  // Moves to a prepared body: the state of now carried over (velocities zeroed when
  // carry_velocities is false), the dependents re-bound. retire: the replaced body is kept
  // to be freed off the stepping thread (takeRetired), else freed here.
  void switchTo(Prepared& p, bool carry_velocities, bool retire);
  // A synchronous change to the forest's active mesh: prepare and switch at once.
  void rebuild(bool persistent_loads);
  // The body the last deferred switch replaced (freed by whoever takes it).
  std::unique_ptr<TissueBody> takeRetired() { return std::move(retired_); }

 private:
  // Volume fractions of the elements of a mesh of the forest (immersed geometry), cached per
  // forest cell (a child of a cell wholly inside is wholly inside; others are sampled).
  void setFractions(const MeshAdaptation& forest, HexMesh& mesh, const std::vector<int>& cells);

  const Scene* scene_;
  std::shared_ptr<const ImmersedGrid> immersed_;  // never changes: copies share it
  std::unordered_map<int, double> cell_fraction_;  // forest cell -> inside fraction (not floored)
  std::unique_ptr<MeshAdaptation> adaptation_;
  std::unique_ptr<TissueBody> body_;
  // The body a deferred switch replaced: freeing it (its factor, matrices and model) took
  // 0.1-0.7 ms, most of a switch step on the phantom; the next background pass or build
  // frees it.
  std::unique_ptr<TissueBody> retired_;
  std::unique_ptr<EmbeddedSurface> organ_;
  std::vector<int> levels_;
  int hanging_ = 0;
  VecX reference_, shifted_;
  const BrainShift* shift_ = nullptr;  // frozen after the pre-step
  double load_scale_ = 1;
  bool loads_with_stiffness_ = false;
  std::atomic<double> stiffness_scale_{1.0};  // read by prepare() on a background thread
  std::function<void(Switch&)> on_switch_;
  std::atomic<bool> lent_{false};
};

}  // namespace needle_sim
