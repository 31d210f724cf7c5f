#include "needle_sim/brain/brain_shift_prestep.hpp"

#include <stdexcept>

#include "needle_sim/adapt/adaptivity_settings.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"

namespace needle_sim {

namespace {

// brain_shift.coarse_start: solves the shift roughly on the grid one level coarser and puts
// its state, interpolated, on the tissue; returns the pass's counts and its load scale
// (coarse_dofs 0 when the scene does not call for it).
BrainShiftResult coarseShiftStart(const PreStepScene& scene, PreStepTissue& tissue) {
  const BrainShiftSettings& settings = scene.settings;
  if (!settings.coarse_start || !scene.grid || scene.grid->refine < 1 || !tissue.target() || !settings.target_shift)
    return {};
  const auto t0 = steadyNow();
  ImmersedGridSettings g = *scene.grid;
  --g.refine;  // the same origin and box: this grid's nodes lie in its box
  std::unique_ptr<TissueBody> coarse;
  BrainShiftResult r;
  // An optional speed-up: whatever fails on the coarse grid (a clamp region selecting none
  // of its nodes, a solve that does not converge, a degenerate mesh) means no start, and
  // this grid solves from rest as without it.
  try {
    const ImmersedGrid grid(scene.surface, g);
    coarse = std::make_unique<TissueBody>(grid.mesh(), scene.tissue, scene.solver, scene.file);
    const EmbeddedSurface organ(scene.surface, coarse->mesh());
    BrainShift shift(settings, scene.tissue, &organ);
    const PointLocator locator(coarse->mesh());
    EmbeddedPoint point;
    const Vec3& rest = tissue.target()->rest;
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
  TissueBody& fine = tissue.body();
  const VecX u = body.displacements();
  VecX x = fine.positions();
  for (int i = 0; i < fine.mesh().numNodes(); ++i) {
    EmbeddedPoint ep;
    const Vec3 p = node3(x, i);
    if (embed(p, ep)) node3(x, i) = p + ep.interpolate(body.mesh(), u);
  }
  fine.setState(x, VecX::Zero(x.size()));
  tissue.checkState();
  r.coarse_dofs = body.mesh().numDofs();
  r.coarse_load_scale = r.load_scale;
  r.ms = msSince(t0);
  return r;
}

}  // namespace

BrainShiftResult runBrainShiftPreStep(const PreStepScene& scene, PreStepTissue& tissue,
                                      std::unique_ptr<BrainShift>& shift) {
  const auto t0 = steadyNow();
  shift = std::make_unique<BrainShift>(scene.settings, scene.tissue, tissue.organ());
  BrainShiftResult total;
  double scale = 1.0;
  bool rough = tissue.adaptive();
  // A uniformly refined grid starts from the shift solved on the grid one level coarser: the
  // controlled solve there finds the load scale and most of the skull's contact set at a
  // fraction of the cost. Its counts and times are part of the totals.
  BrainShiftResult coarse = tissue.adaptive() ? BrainShiftResult{} : coarseShiftStart(scene, tissue);
  if (coarse.coarse_dofs > 0) {
    scale = coarse.coarse_load_scale;
    total.newton_iterations = coarse.newton_iterations;
    total.factorizations = coarse.factorizations;
    total.load_solves = coarse.load_solves;
    total.multiplier_updates = coarse.multiplier_updates;
    total.restarts = coarse.restarts;
    total.factor_ms = coarse.factor_ms;
    total.solve_ms = coarse.solve_ms;
  }
  for (int pass = 1;; ++pass) {
    // The coarse mesh's first pass only shows where to refine: its load scale (which the
    // refined meshes change severalfold, the clamps holding more nodes) is not solved for.
    auto solve = [&] { return shift->apply(tissue.body(), tissue.target(), scale, rough, !(rough && pass == 1)); };
    BrainShiftResult r;
    try {
      r = solve();
    } catch (const NumericalError&) {
      if (coarse.coarse_dofs == 0) throw;
      // The coarse start led the solve astray: from rest, as without it.
      TissueBody& body = tissue.body();
      body.setState(body.mesh().restPositions(), VecX::Zero(body.mesh().numDofs()));
      body.resetExternalForce();
      shift = std::make_unique<BrainShift>(scene.settings, scene.tissue, tissue.organ());
      coarse = BrainShiftResult{};
      total = BrainShiftResult{};
      scale = 1.0;
      r = solve();
    }
    const int iterations = total.newton_iterations + r.newton_iterations;
    const int factorizations = total.factorizations + r.factorizations;
    const int solves = total.load_solves + r.load_solves, updates = total.multiplier_updates + r.multiplier_updates;
    const int restarts = total.restarts + r.restarts;
    const double fms = total.factor_ms + r.factor_ms, sms = total.solve_ms + r.solve_ms;
    total = r;
    total.newton_iterations = iterations;
    total.factorizations = factorizations;
    total.load_solves = solves;
    total.multiplier_updates = updates;
    total.restarts = restarts;
    total.factor_ms = fms;
    total.solve_ms = sms;
    total.passes = pass;
    scale = r.load_scale;
    tissue.checkState();
    if (!rough) break;
    const bool changed = pass < kMaxStaticAdaptationPasses && tissue.adapt();
    if (!changed) {
      // Final solve on this mesh, from the rough state (apply adds its loads afresh).
      rough = false;
      tissue.body().resetExternalForce();
    }
    shift->rebind(tissue.organ());
  }
  if (tissue.target()) total.target = scene.settings.target;
  total.ms = msSince(t0);
  total.coarse_dofs = coarse.coarse_dofs;
  total.coarse_newton_iterations = coarse.newton_iterations;
  total.coarse_factorizations = coarse.factorizations;
  total.coarse_ms = coarse.ms;
  total.coarse_load_scale = coarse.coarse_load_scale;
  return total;
}

}  // namespace needle_sim
