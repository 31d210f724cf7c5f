#include "needle_sim/brain/brain_shift.hpp"

#include <algorithm>
#include <cmath>
#include <optional>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/fem/hex8.hpp"

namespace needle_sim {

namespace {
// Relative residual of a rough solve (a pass of the adaptive pre-step that only feeds the
// error estimate).
constexpr double kRoughTolerance = 1e-3;
// Relative residual of the solves between multiplier updates (inexact Uzawa): a tenth of the
// rough passes', enough for the penetration they measure (the displacement's error about
// 1e-4 of the shift, 2 um on the DBS scenes, against a penetration tolerance of 10 um).
constexpr double kUzawaTolerance = 1e-4;
// A controlled Newton step presses a vertex that was off at most this fraction of the gap
// into the skull, and is never cut below kMinStep of its length.
constexpr double kStepDepth = 0.1;
constexpr double kMinStep = 0.05;
// From rest under target_shift, a first load step whose static solve fails is tried again
// from rest at this fraction of the load, up to kRetries times (a brain 10x softer than the
// scenes' needs about 1/8 of the gravity for the shift; 1/512 reaches one 100x softer).
constexpr double kRetryScale = 0.125;
constexpr int kRetries = 3;
}  // namespace

BrainShift::BrainShift(const BrainShiftSettings& settings, const TissueParameters& tissue, const EmbeddedSurface* organ)
    : settings_(settings), density_(settings.density.value_or(tissue.material.density)), organ_(organ) {
  if (organ_ && settings_.skull_contact)
    skull_.emplace(*organ_, settings_.skull.get(), settings_.gap, tissue.material.young);
}

const std::vector<Vec3>& BrainShift::skullForces() const {
  static const std::vector<Vec3> none;
  return skull_ ? skull_->reactions() : none;
}

VecX BrainShift::unitLoad(const TissueBody& body) const {
  const HexMesh& mesh = body.mesh();
  const CorotationalHexModel& model = body.model();
  VecX f = VecX::Zero(mesh.numDofs());
  const Vec3 up = -settings_.gravity.normalized();
  const Vec3 b = density_ * settings_.gravity;  // N/m^3
  for (int e = 0; e < mesh.numElements(); ++e) {
    // Only the part above the CSF level has lost its buoyancy: the fraction of the cell
    // above the plane (sampled in cells it cuts, so that coarse and refined meshes carry the
    // same load).
    double above = 1;
    if (!settings_.all) {
      const Eigen::Matrix<double, 8, 3> X = mesh.elementCorners(e);
      // Height of each corner above the CSF level; inside the element the height is their
      // trilinear interpolation (the map is trilinear, the height linear in space).
      hex8::Vec8 h;
      int n_above = 0;
      for (int a = 0; a < 8; ++a) {
        h[a] = up.dot(X.row(a).transpose() - settings_.csf_point);
        n_above += h[a] > 0;
      }
      if (n_above == 0) continue;  // still buoyant in CSF
      if (n_above < 8) {
        // kS^3 samples at the centres of a regular grid in natural coordinates. Along each
        // line of samples in zeta the height is linear: two interpolations per line.
        constexpr int kS = 16;
        int hits = 0;
        for (int i = 0; i < kS; ++i)
          for (int j = 0; j < kS; ++j) {
            const double xi = 2 * (i + 0.5) / kS - 1, eta = 2 * (j + 0.5) / kS - 1;
            const double h0 = hex8::shape(Vec3(xi, eta, -1)).dot(h), h1 = hex8::shape(Vec3(xi, eta, 1)).dot(h);
            for (int k = 0; k < kS; ++k) {
              const double t = (k + 0.5) / kS;
              hits += (1 - t) * h0 + t * h1 > 0;
            }
          }
        above = static_cast<double>(hits) / (kS * kS * kS);
      }
    }
    const auto& nv = model.reference(e).node_volume;  // weighted by the volume fraction
    for (int a = 0; a < 8; ++a) node3(f, mesh.element(e)[a]) += above * nv[a] * b;
  }
  return f;
}

BrainShiftResult BrainShift::apply(TissueBody& body, const EmbeddedPoint* target, double start_scale, bool rough,
                                   bool calibrate) {
  const auto t0 = steadyNow();
  BrainShiftResult res;
  const VecX unit = unitLoad(body);
  const bool with_contact = skull_ && skull_->numVertices() > 0;
  if (with_contact) skull_->setRest(body.mesh());
  // 0.1 % of the gap (1 % on a rough pass)
  const double pen_tol = (rough ? 1e-2 : 1e-3) * std::max(settings_.gap, 1e-3 * SkullContact::cellSize(body.mesh()));
  TissueBody::ExtraForce extra;
  if (with_contact)
    extra = [this, &body](const VecX& x, VecX& f, ElementBlocks& K) { skull_->addForces(body.mesh(), x, f, K); };

  // The load steps and multiplier updates below solve on nearly the same tangent: each starts
  // from the factor the last one left (and refactorises when the contact set moved).
  struct KeepFactor {
    TissueBody& b;
    explicit KeepFactor(TissueBody& body) : b(body) { b.keepStaticFactor(true); }
    ~KeepFactor() { b.keepStaticFactor(false); }
  } keep_factor(body);
  // Under displacement control a Newton step moves the load a lot (7x on the DBS meshes) with
  // the tangent of the contacts it had: vertices that were off would plunge deep into the
  // skull, and the next steps spend a factorisation each pulling them back. Each step is cut
  // so that no vertex that was off presses in more than 10 % of the gap (doc/method.md
  // "Brain shift"; dbs_fine 25 -> 22 factorisations, dbs_adaptive 44 -> 41).
  TissueBody::StepLimit limit;
  if (with_contact) {
    const double depth = kStepDepth * std::max(settings_.gap, 1e-3 * SkullContact::cellSize(body.mesh()));
    limit = [this, &body, depth](const VecX& x, const VecX& dx) {
      return skull_->stepLimit(body.mesh(), x, dx, depth, kMinStep);
    };
  }
  double applied = 0;  // scale of the load now in the body
  const double tol = rough ? std::max(settings_.tolerance, kRoughTolerance) : settings_.tolerance;
  // Newton solves with multiplier updates until the penetration is within tolerance.
  // loose: to the rough tolerances (the steps towards target_shift's scale).
  auto solveContact = [&](bool loose, TissueBody::LoadControl* control) {
    loose = loose || rough;
    // Inexact Uzawa: a solve whose multipliers are updated after it needs no more digits than
    // the penetration it measures; only the last, with the multipliers that hold the skull
    // within tolerance, is solved to the full tolerance (continuing from the inexact one).
    bool inexact = with_contact && !loose && tol < kUzawaTolerance;
    for (int pass = 0; pass < (loose ? 2 : 20); ++pass) {
      // (Not on the load steps from rest: there backtracking on the residual does the same,
      // and the cut steps cost more Newton steps than they saved factorisations.)
      const double solve_tol = loose ? std::max(tol, kRoughTolerance) : inexact ? kUzawaTolerance : tol;
      const StepStats st = body.solveStatic(extra, solve_tol, 50, control,
                                            control ? limit : TissueBody::StepLimit{});
      res.newton_iterations += st.newton_iterations;
      res.factorizations += st.factorizations;
      res.factor_ms += st.factor_ms + st.assemble_ms;
      res.solve_ms += st.solve_ms + st.forces_ms;
      if (!with_contact) break;
      int active = 0;
      const double pen = skull_->penetration(body.mesh(), body.positions(), active);
      if (pen <= pen_tol) {
        if (!inexact) break;
        inexact = false;  // the same multipliers, now to the full tolerance
        --pass;           // (not a round of its own)
        continue;
      }
      ++res.multiplier_updates;
      skull_->updateMultipliers(body.mesh(), body.positions());
    }
    ++res.load_solves;
  };
  auto setScale = [&](double scale) {
    body.addExternalForce((scale - applied) * unit);
    applied = scale;
  };
  auto targetMotion = [&]() { return target ? Vec3(target->interpolate(body.mesh(), body.positions()) - target->rest) : Vec3::Zero(); };

  try {
    const bool at_rest = (body.positions() - body.mesh().restPositions()).squaredNorm() == 0;
    const bool control = calibrate && settings_.target_shift && target;
    // From rest, the load in steps (the controlled solve needs the target to have moved to
    // know its direction); from an earlier shift (a refined mesh), the controlled solve at once.
    const int steps = at_rest ? settings_.load_steps : control ? 0 : 1;
    const VecX x0 = body.positions(), v0 = body.velocities();
    const std::optional<SkullContact> skull0 = skull_;
    for (int retry = 0;; ++retry) {
      const double scale0 = start_scale * std::pow(kRetryScale, retry);
      try {
        if (steps == 0) setScale(scale0);
        for (int k = 1; k <= steps; ++k) {
          setScale(scale0 * k / steps);
          solveContact(control, nullptr);  // rough when the scale is solved for next
        }
        break;
      } catch (const NumericalError&) {
        // The whole load moves a soft brain by centimetres, further than Newton reaches
        // (E = 195 Pa in the ensemble study, doc/ensemble.md): with target_shift the scale
        // is solved for (next, or on the next pass of an adaptive pre-step) anyway, so start
        // again from rest at a fraction of it.
        if (!(at_rest && settings_.target_shift && target) || retry == kRetries) throw;
        body.setState(x0, v0);
        skull_ = skull0;
        body.keepStaticFactor(false);
        body.keepStaticFactor(true);
        ++res.restarts;
      }
    }
    res.load_scale = applied;
    if (control) {
      // target_shift: displacement control, |d(x)| = want with the load scale unknown (the
      // bordered Newton of TissueBody::solveStatic), to 1 % on a rough pass, 0.1 % else.
      const double want = *settings_.target_shift;
      const double accuracy = rough ? 1e-2 : 1e-3;
      const HexMesh& mesh = body.mesh();
      const auto& el = mesh.element(target->element);
      TissueBody::LoadControl lc;
      lc.unit = &unit;
      lc.scale = applied;
      lc.tolerance = 0.25 * accuracy * want;
      lc.constraint = [&](const VecX& x, VecX& g) {
        const Vec3 d = target->interpolate(mesh, x) - target->rest;
        const double n = d.norm();
        if (!(n > 0)) throw NumericalError(-1, "brain shift: the target does not move with the load");
        for (int a = 0; a < 8; ++a) node3(g, el[a]) += target->weights[a] * d / n;
        return n - want;
      };
      try {
        solveContact(rough, &lc);
      } catch (const NumericalError& e) {
        throw NumericalError(-1, "brain shift: could not reach target_shift " + std::to_string(want) + " m (" +
                                     e.what() + ")");
      }
      applied = lc.scale;
      const double got = targetMotion().norm();
      if (std::abs(got - want) > accuracy * want)
        throw NumericalError(-1, "brain shift: could not reach target_shift " + std::to_string(want) + " m (got " +
                                     std::to_string(got) + " m)");
      res.load_scale = applied;
    }
  } catch (const NumericalError& e) {
    throw NumericalError(0, std::string(e.what()) + " (brain-shift pre-step)");
  }

  // Freeze the skull reactions as loads: the shifted state is then an equilibrium without
  // the contact terms.
  if (with_contact) {
    Vec3 total;
    body.addExternalForce(skull_->freeze(body.mesh(), body.positions(), total));
    res.skull_force = total.norm();
    res.max_penetration = skull_->penetration(body.mesh(), body.positions(), res.contacts);
  }
  if (target) res.target_displacement = target->interpolate(body.mesh(), body.positions()) - target->rest;
  res.max_displacement = 0;
  const VecX u = body.displacements();
  for (int i = 0; i < body.mesh().numNodes(); ++i) res.max_displacement = std::max(res.max_displacement, node3(u, i).norm());
  res.done = true;
  res.passes = 1;
  res.dofs = body.mesh().numDofs();
  res.ms = msSince(t0);
  return res;
}

VecX BrainShift::skullLoad(const TissueBody& body, const EmbeddedSurface& organ) const {
  return skull_ ? skull_->frozenLoad(body.mesh(), organ) : VecX::Zero(body.mesh().numDofs());
}

ElementBlocks BrainShift::supportStiffness(const EmbeddedSurface& organ) const {
  return hasSupport() ? skull_->supportStiffness(organ) : ElementBlocks{};
}

VecX BrainShift::supportAnchorLoad(const TissueBody& body, const EmbeddedSurface& organ) const {
  return hasSupport() ? skull_->supportAnchorLoad(body.mesh(), organ) : VecX::Zero(body.mesh().numDofs());
}

void BrainShift::applySupport(TissueBody& body, const EmbeddedSurface* organ) const {
  if (!organ || !hasSupport()) return;
  body.setSupport(supportStiffness(*organ));
  body.addExternalForce(supportAnchorLoad(body, *organ));
}

VecX BrainShift::shiftLoad(const TissueBody& body, const EmbeddedSurface* organ, double load_scale) const {
  VecX f = load_scale * unitLoad(body);
  if (organ) f += skullLoad(body, *organ);
  return f;
}

void BrainShift::applyPersistentLoads(TissueBody& body, const EmbeddedSurface* organ, double load_scale,
                                      double factor) const {
  VecX f = shiftLoad(body, organ, load_scale);
  if (factor != 1.0) f *= factor;
  body.addExternalForce(f);
  applySupport(body, organ);
}

}  // namespace needle_sim
