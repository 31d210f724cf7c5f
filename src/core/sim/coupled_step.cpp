#include "needle_sim/sim/coupled_step.hpp"

#include <string>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

StepStats coupledStep(const CoupledBodies& b, double time, double dt, bool dynamic) {
  StepStats stats;
  auto add = [&](const StepStats& s) { stats.accumulate(s); };
  if (b.interaction) {
    // free motion of every body, constraint solve and corrections, commit, law updates
    const double h = dt;
    add(b.tissue->freeMotion(h));
    for (auto& nd : *b.needles) add(nd->freeMotion(time, h));
    const InteractionStats is = b.interaction->solve(h);
    stats.constraint_points = is.points;
    stats.constraint_iterations = is.iterations;
    stats.constraint_residual = is.residual;
    stats.constraint_converged = is.converged;
    stats.constraint_ms = is.ms;
    b.tissue->commit(h);
    for (auto& nd : *b.needles) nd->commit(time, h);
    b.interaction->afterCommit();
  } else {
    if (b.tissue) add(dynamic ? b.tissue->stepDynamic(dt) : b.tissue->solveStatic());
    for (auto& nd : *b.needles) add(dynamic ? nd->stepDynamic(time, dt) : nd->solveStatic(time + dt));
  }
  return stats;
}

void checkBodies(const TissueBody* tissue, const std::vector<std::unique_ptr<NeedleBody>>& needles, long step,
                 double tissue_size) {
  for (const auto& nd : needles) {
    for (int i = 0; i < nd->beam().numNodes(); ++i)
      if (!nd->state().p[i].allFinite() || !nd->state().q[i].coeffs().allFinite())
        throw NumericalError(step, "needle '" + nd->name() + "': non-finite state at step " + std::to_string(step));
    const double reach = (nd->tipPosition() - nd->state().p[0]).norm();
    if (reach > 2 * nd->beam().length())
      throw NumericalError(step, "needle '" + nd->name() + "' diverged at step " + std::to_string(step) +
                                     ": tip " + std::to_string(reach) + " m from the base");
  }
  if (!tissue) return;
  const VecX& x = tissue->positions();
  const VecX& v = tissue->velocities();
  if (!x.allFinite() || !v.allFinite())
    throw NumericalError(step, "non-finite positions or velocities at step " + std::to_string(step));
  const double umax = tissue->displacements().lpNorm<Eigen::Infinity>();
  if (umax > 10 * tissue_size)
    throw NumericalError(step, "divergence at step " + std::to_string(step) + ": displacement " +
                                   std::to_string(umax) + " m exceeds 10x the tissue size");
}

}  // namespace needle_sim
