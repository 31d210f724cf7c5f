#pragma once
// The brain-shift pre-step as a simulation runs it (doc/method.md, "Brain shift"): the
// static solve of brain_shift.hpp on the tissue in use, and on an adaptive mesh alternated
// with adaptation passes — solve, estimate, refine/coarsen, solve again on the new mesh from
// the shifted state and the last load scale — until the mesh stays as it is, so the insertion
// starts from the shift computed on the mesh the estimate asks for. The passes before the
// last solve roughly (the estimate needs the stress pattern, not the last digit); the last
// one, on the final mesh, solves to the tolerance and scales the load for target_shift.
// On a uniformly refined immersed grid the solve starts from the shift solved roughly on the
// grid one level coarser (brain_shift.coarse_start, nested iteration).
#include <memory>
#include <string>

#include "needle_sim/brain/brain_shift.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/solver/solver_settings.hpp"

namespace needle_sim {

// The tissue the pre-step solves on, as the simulation holds it.
class PreStepTissue {
 public:
  virtual ~PreStepTissue() = default;
  virtual TissueBody& body() = 0;
  virtual const EmbeddedSurface* organ() const = 0;
  // The shift's target, embedded in the mesh in use, or nullptr.
  virtual const EmbeddedPoint* target() const = 0;
  virtual bool adaptive() const = 0;
  // One adaptation pass on the current state; true when the mesh changed: the body is then
  // on the new mesh with the state carried over, the velocities zero and no load applied.
  virtual bool adapt() = 0;
  // Throws NumericalError for a non-finite or diverged state.
  virtual void checkState() const = 0;
};

// What the pre-step reads of the scene.
struct PreStepScene {
  const BrainShiftSettings& settings;
  const TissueParameters& tissue;
  const SolverSettings& solver;
  const std::string& file;
  // An immersed grid's surface and grid (the coarse start), or null.
  std::shared_ptr<const TriangleMesh> surface;
  const ImmersedGridSettings* grid = nullptr;
};

// Runs the pre-step on `tissue`; `shift` is the BrainShift it made (its skull state and
// loads are the caller's from then on). Throws NumericalError when it fails.
BrainShiftResult runBrainShiftPreStep(const PreStepScene& scene, PreStepTissue& tissue,
                                      std::unique_ptr<BrainShift>& shift);

}  // namespace needle_sim
