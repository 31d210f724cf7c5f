#pragma once
// One step of the coupled bodies (doc/method.md, "Time integration", "Constraint solve"):
// with a needle-tissue interaction, every body's free motion, the constraint solve with its
// corrections, the commit and the constraint laws' updates (paper §2.2); without one, each
// body's own dynamic step or static solve. And the check every step ends with: a non-finite
// or diverged state is a NumericalError, never a result.
#include <memory>
#include <vector>

#include "needle_sim/contact/needle_tissue_interaction.hpp"
#include "needle_sim/core/step_stats.hpp"
#include "needle_sim/needle/needle_body.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

struct CoupledBodies {
  TissueBody* tissue = nullptr;  // nullptr: needles only
  std::vector<std::unique_ptr<NeedleBody>>* needles = nullptr;
  NeedleTissueInteraction* interaction = nullptr;
};

// Advances the bodies from `time` by dt (dynamic) or solves the load step at time + dt
// (static). Throws NumericalError on a failed solve.
StepStats coupledStep(const CoupledBodies& bodies, double time, double dt, bool dynamic);

// Throws NumericalError(step) for a non-finite state, a needle whose tip left its base by
// more than twice its length, or tissue displacements beyond ten times `tissue_size`.
void checkBodies(const TissueBody* tissue, const std::vector<std::unique_ptr<NeedleBody>>& needles, long step,
                 double tissue_size);

}  // namespace needle_sim
