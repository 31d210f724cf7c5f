// TissueBody's static solve: Newton on the corotational forces to equilibrium, with extra
// conservative terms (skull contact) and optionally displacement control (load_control.hpp),
// inexact (the CG tolerance follows the residual). doc/method.md, "Static solves".
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <unordered_map>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/tissue/tissue_body.hpp"

namespace needle_sim {

namespace {
std::string fmtSci(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%.3e", v);
  return b;
}

// Number of elements whose blocks (summed) differ between a and b beyond round-off.
int changedBlocks(const ElementBlocks& a, const ElementBlocks& b) {
  auto differ = [](const hex8::Mat24& p, const hex8::Mat24& q) {
    return (p - q).cwiseAbs().maxCoeff() > 1e-12 * std::max(p.cwiseAbs().maxCoeff(), q.cwiseAbs().maxCoeff());
  };
  if (a.element == b.element) {  // the same elements in the same order (an unchanged contact set): no map
    int n = 0;
    for (size_t i = 0; i < a.K.size(); ++i) n += differ(a.K[i], b.K[i]);
    return n;
  }
  std::unordered_map<int, std::pair<hex8::Mat24, hex8::Mat24>> sum;
  auto add = [&](const ElementBlocks& blocks, bool first) {
    for (size_t i = 0; i < blocks.element.size(); ++i) {
      auto [it, fresh] = sum.try_emplace(blocks.element[i], hex8::Mat24::Zero(), hex8::Mat24::Zero());
      (first ? it->second.first : it->second.second) += blocks.K[i];
    }
  };
  add(a, true);
  add(b, false);
  int n = 0;
  for (const auto& [e, ab] : sum) n += differ(ab.first, ab.second);
  return n;
}

// Restores the solver's persistent extra stiffness (the support) and drops its factor when
// a solve with temporary blocks ends (unless the body keeps it for the next static solve:
// keep, set when the solve succeeded).
struct Detach {
  SystemSolver& s;
  const ElementBlocks* base;
  bool keep = false;
  ~Detach() {
    s.setNonsymmetricTerm(nullptr);
    s.setExtraStiffness(base);
    if (!keep) s.invalidate();
  }
};

// Static Newton refreshes its factor on this thread (SystemSolver::setAsync); the dynamic
// steps after it get their background refreshes back.
struct SynchronousRefresh {
  SystemSolver& s;
  const bool was;
  explicit SynchronousRefresh(SystemSolver& solver) : s(solver), was(solver.async()) { s.setAsync(false); }
  ~SynchronousRefresh() { s.setAsync(was); }
};
}  // namespace

void TissueBody::keepStaticFactor(bool on) {
  keep_static_factor_ = on;
  if (on) return;
  if (static_factor_blocks_) solver_->invalidate();
  static_factor_blocks_.reset();
}

StepStats TissueBody::solveStatic() {
  return solveStatic(ExtraForce{}, settings_.static_tolerance, settings_.static_max_iterations);
}

// Full Newton steps under load control before falling back to backtracking (a safeguard
// against an active set that cycles).
constexpr int kFullControlledSteps = 20;

StepStats TissueBody::solveStatic(const ExtraForce& extra, double tol, int max_iterations, LoadControl* control,
                                  const StepLimit& limit) {
  StepStats st;
  VecX r_full, r, dx_free, dx, unit_free, w_free, w, grad_full, grad;
  ElementBlocks blocks;
  auto loadNorm = [&]() {
    VecX fe;
    dofs_.gather(f_ext_, fe);
    return fe.norm();
  };
  double ref = loadNorm(), rn0 = 0;
  // The consistent tangent: the rotation part in the Newton steps' operator (GMRES), the
  // factor of the symmetric part as their preconditioner (doc/method.md "Static solves";
  // pcg only: a direct solve uses the factor alone). Declared before `detach`, which clears
  // the solver's pointer to it.
  CorotationalHexModel::RotationTerms rotation_terms;
  const SystemSolver::OperatorTerm rotation_product = [&](const VecX& v, double s, VecX& out) {
    model_->addRotationStiffnessProduct(rotation_terms, v, s, out);
  };
  const bool rotation_tangent =
      settings_.static_rotation_tangent && settings_.linear.method == LinearSolverSettings::Method::Pcg;
  Detach detach{*solver_, supportOrNull()};  // the solver must not keep `blocks` past this call
  SynchronousRefresh synchronous(*solver_);
  if (rotation_tangent) solver_->setNonsymmetricTerm(&rotation_product);
  // Residual (free DOFs) at the current x_, with the extra terms' blocks.
  auto residual = [&](VecX& out) {
    model_->updateRotations(x_);
    if (rotation_tangent) model_->rotationTerms(x_, rotation_terms);
    r_full = f_ext_;
    model_->addInternalForce(x_, r_full);
    addSupportProduct(x_, 1.0, r_full);
    if (extra) {
      blocks.clear();
      extra(x_, r_full, blocks);
      blocks.element.insert(blocks.element.end(), support_.element.begin(), support_.element.end());
      blocks.K.insert(blocks.K.end(), support_.K.begin(), support_.K.end());
    }
    dofs_.gather(r_full, out);
    return out.norm();
  };
  // Load control: the constraint at x_, its gradient over the free DOFs, and the load scale.
  double c = 0;
  auto constraint = [&]() {
    grad_full.setZero(x_.size());
    c = control->constraint(x_, grad_full);
    dofs_.gather(grad_full, grad);
    if (!std::isfinite(c)) throw NumericalError(-1, "static solve: load-control constraint is NaN/Inf");
  };
  auto setScale = [&](double s) {
    f_ext_ += (s - control->scale) * *control->unit;
    control->scale = s;
  };
  if (control) {
    if (!control->unit || !control->constraint || !(control->scale > 0) || !(control->max_growth > 1) ||
        !(control->tolerance > 0))
      throw std::invalid_argument("LoadControl needs a unit load, a constraint, a scale > 0, max_growth > 1 and a tolerance > 0");
    dofs_.gather(*control->unit, unit_free);
    w_free.setZero(unit_free.size());
  }
  // The extra blocks in the factor: those the last static solve left when the body keeps its
  // factor (keepStaticFactor), else none (the first solve refactorises as they differ).
  ElementBlocks factor_blocks = static_factor_blocks_.value_or(ElementBlocks{});
  static_factor_blocks_.reset();
  VecX x_trial, r_trial;
  double rn = 0, gw = 1;
  const double lin_tol = solver_->settings().tolerance;
  bool tight = true;  // the last correction was solved to the solver's own tolerance
  bool cut = false;   // the last step was cut by the limit (its length says nothing of convergence)
  bool refactor_next = false;
  for (int it = 0; it <= max_iterations; ++it) {
    auto t0 = steadyNow();
    if (it == 0) {
      rn = residual(r);
      if (control) constraint();
    }
    if (extra) solver_->setExtraStiffness(&blocks);
    if (it == 0) rn0 = rn;
    // Relative to the load now in the body (under control its scale changes, either way).
    ref = std::max(control ? loadNorm() : ref, rn0);
    st.forces_ms += msSince(t0);
    st.newton_residual = ref > 0 ? rn / ref : 0.0;
    if (!std::isfinite(rn)) throw NumericalError(-1, "static solve: residual is NaN/Inf");
    // Converged when the residual is small, or when the last Newton correction is below the
    // requested accuracy of the displacement (on ill-conditioned problems such as slender
    // cantilevers the residual bottoms out near cond(K) * eps before the solution does);
    // under load control also when the constraint holds.
    // An inexact correction (CG from zero) underestimates the Newton step: a small one is
    // trusted only when solved to the solver's own tolerance, else it is solved again so.
    const double un = (x_ - rest_).norm();
    const bool small_step = it > 0 && !cut && dx.norm() <= tol * un;
    const bool balanced = rn <= tol * ref || ref == 0 || (small_step && tight);
    if (balanced && (!control || std::abs(c) <= control->tolerance)) {
      st.newton_iterations = it;
      v_.setZero();
      if (keep_static_factor_) {
        static_factor_blocks_ = std::move(factor_blocks);
        detach.keep = true;
      }
      return st;
    }
    if (it == max_iterations) break;
    dx_free.setZero(r.size());
    // Inexact Newton: far from equilibrium the step needs few digits (the forcing term
    // follows the residual, which keeps the convergence superlinear), and the last step
    // only as many as the tolerance asks for. Never looser than 1e-1, never tighter than
    // the solver's own tolerance.
    const double rel = ref > 0 ? rn / ref : 0.0;
    double eta = rel > 0 ? std::clamp(std::max(std::min(1e-2, rel), 0.5 * tol / rel), lin_tol, std::max(1e-1, lin_tol))
                         : lin_tol;
    if (small_step) eta = lin_tol;
    tight = eta <= lin_tol;
    // The last correction's CG ran out of its budget on the stale factor (the contact set or
    // the load moved the tangent far): this one's tangent has moved as far, so refactorise
    // at once instead of paying the budget again first.
    // The extra terms' blocks changed since the factor was made (contacts switched on or
    // off: each a stiff change that costs CG an iteration or more on the old factor): when
    // more changed than the iterations that make a factor stale, refactorise at once rather
    // than pay CG's budget first.
    if (refactor_next || (extra && changedBlocks(factor_blocks, blocks) > solver_->settings().refresh_iterations))
      solver_->invalidate();
    // Counts a solve and, when it refactorised, records the blocks its factor holds.
    auto account = [&](const LinearSolveStats& l) {
      if (l.refactored && extra) factor_blocks = blocks;
      accumulate(st, l);
    };
    const LinearSolveStats ls = solver_->solve(mass_free_, 0.0, 1.0, r, dx_free, eta);
    refactor_next = ls.budget_exhausted;
    account(ls);
    double ds = 0;
    if (control) {
      // w = K^-1 unit (warm-started from the last one: K changes little between steps), then
      // the scale change that satisfies the linearised constraint.
      account(solver_->solve(mass_free_, 0.0, 1.0, unit_free, w_free, std::max(std::min(eta, 1e-3), lin_tol)));
      gw = grad.dot(w_free);
      if (!(gw > 0)) throw NumericalError(-1, "static solve: the controlled displacement does not grow with the load");
      ds = -(c + grad.dot(dx_free)) / gw;
      const double s = control->scale;
      ds = std::clamp(ds, s / control->max_growth - s, s * control->max_growth - s);
      dx_free += ds * w_free;
    }
    dofs_.scatter(dx_free, dx);
    t0 = steadyNow();
    // The part of the step the extra terms allow (e.g. new skull contacts pressing in).
    const double a = limit ? limit(x_, dx) : 1.0;
    cut = a < 1;
    if (cut) {
      dx *= a;
      ds *= a;
    }
    if (!extra && !control) {
      x_ += dx;
      rn = residual(r);
    } else if (control && it < kFullControlledSteps) {
      // Under load control the full step: the load moves a lot at first and the contact set
      // with it, which the next step's tangent then holds (semi-smooth Newton); backtracking
      // crawled here (each step cut to a few per cent by the penetrations it caused).
      x_ += dx;
      setScale(control->scale + ds);
      constraint();
      rn = residual(r);
    } else {
      // The extra terms (contact) switch on and off: a full step can overshoot into a far
      // worse residual. Backtrack on the residual norm (a few cheap force evaluations save
      // factorisations); under load control the constraint's violation counts as the load
      // that would remove it.
      const double c_weight = control ? unit_free.norm() / gw : 0.0;
      const double merit = rn + c_weight * std::abs(c);
      const double s0 = control ? control->scale : 0.0;
      x_trial = x_;
      double alpha = 1;
      for (int k = 0; k < 6; ++k, alpha *= 0.5) {
        x_ = x_trial + alpha * dx;
        if (control) {
          setScale(s0 + alpha * ds);
          constraint();
        }
        const double rt = residual(r_trial);
        if (rt + c_weight * std::abs(c) < merit || k == 5) {
          rn = rt;
          r.swap(r_trial);
          break;
        }
      }
      dx *= alpha;
    }
    if (control && control->scale > control->max_scale)
      throw NumericalError(-1, "static solve: the load scale passed " + fmtSci(control->max_scale) +
                                   " (the controlled displacement is out of reach)");
    st.forces_ms += msSince(t0);
  }
  throw NumericalError(-1, "static solve did not converge in " + std::to_string(max_iterations) +
                               " Newton iterations (relative residual " + fmtSci(st.newton_residual) + ")");
}

}  // namespace needle_sim
