#include "needle_sim/sim/tissue_body.hpp"

#include <algorithm>
#include <stdexcept>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

namespace {
double msSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

std::string fmtSci(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%.3e", v);
  return b;
}

// Consistent nodal forces of a uniform traction on a bilinear quadrilateral face.
void addFaceTraction(const HexMesh& mesh, const BoundaryFace& f, const Vec3& t, VecX& out) {
  const double g = 1.0 / std::sqrt(3.0);
  static const double sgn[4][2] = {{-1, -1}, {1, -1}, {1, 1}, {-1, 1}};
  for (int i = 0; i < 4; ++i) {
    const double s = sgn[i][0] * g, r = sgn[i][1] * g;
    Vec3 ds = Vec3::Zero(), dr = Vec3::Zero();
    double N[4];
    for (int q = 0; q < 4; ++q) {
      N[q] = 0.25 * (1 + sgn[q][0] * s) * (1 + sgn[q][1] * r);
      ds += 0.25 * sgn[q][0] * (1 + sgn[q][1] * r) * mesh.node(f.nodes[q]);
      dr += 0.25 * sgn[q][1] * (1 + sgn[q][0] * s) * mesh.node(f.nodes[q]);
    }
    const double dA = ds.cross(dr).norm();
    for (int q = 0; q < 4; ++q) node3(out, f.nodes[q]) += t * (N[q] * dA);
  }
}
}  // namespace

TissueBody::TissueBody(const TissueBody& o)
    : mesh_(std::make_unique<HexMesh>(*o.mesh_)),
      settings_(o.settings_),
      dofs_(o.dofs_),
      rest_(o.rest_),
      x_(o.x_),
      v_(o.v_),
      f_ext_(o.f_ext_),
      mass_(o.mass_),
      mass_free_(o.mass_free_),
      scene_f_ext_(o.scene_f_ext_),
      dv_free_(o.dv_free_),
      support_(o.support_),
      columns_(o.columns_) {
  model_ = std::make_unique<CorotationalHexModel>(*o.model_, *mesh_);
  solver_ = std::make_unique<SystemSolver>(*o.solver_, *model_, dofs_);
  solver_->setExtraStiffness(supportOrNull());
}

TissueBody::TissueBody(HexMesh mesh, const TissueScene& tissue, const SolverScene& solver, const std::string& file,
                       const std::vector<std::vector<std::pair<int, double>>>& node_hanging)
    : mesh_(std::make_unique<HexMesh>(std::move(mesh))), settings_(solver) {
  model_ = std::make_unique<CorotationalHexModel>(*mesh_, tissue.material);
  const int n = mesh_->numNodes();
  rest_ = mesh_->restPositions();
  x_ = rest_;
  v_ = VecX::Zero(3 * n);
  const double tol = 1e-8 * (mesh_->boundsMax() - mesh_->boundsMin()).norm();

  // Dirichlet conditions: later conditions override earlier ones on shared nodes.
  std::vector<char> prescribed(3 * n, 0);
  for (const auto& dc : tissue.dirichlet) {
    int count = 0;
    for (int i = 0; i < n; ++i)
      if (dc.region.contains(mesh_->node(i), tol)) {
        ++count;
        for (int d = 0; d < 3; ++d)
          if (dc.components[d]) {
            prescribed[3 * i + d] = 1;
            x_[3 * i + d] = rest_[3 * i + d] + dc.displacement[d];
          }
      }
    if (count == 0) throw InputError(file, dc.key + ".region", "selects no grid node of the tissue");
  }
  if (node_hanging.empty()) {
    dofs_ = DofMap(prescribed);
  } else {
    std::vector<std::vector<std::pair<int, double>>> hanging(3 * n);
    for (int i = 0; i < n && i < static_cast<int>(node_hanging.size()); ++i)
      for (const auto& [m, w] : node_hanging[i])
        for (int d = 0; d < 3; ++d) hanging[3 * i + d].emplace_back(3 * m + d, w);
    dofs_ = DofMap(prescribed, hanging);
    dofs_.interpolateHanging(x_);  // follow prescribed masters
  }

  // Loads: gravity and body force through the lumped (row-sum) mass, tractions on faces.
  const VecX& vol = model_->nodalVolume();
  mass_.resize(3 * n);
  f_ext_.setZero(3 * n);
  const double rho = tissue.material.density;
  for (int i = 0; i < n; ++i) {
    mass_.segment<3>(3 * i).setConstant(rho * vol[i]);
    node3(f_ext_, i) = vol[i] * (rho * tissue.gravity + tissue.body_force);
  }
  if (!tissue.tractions.empty()) {
    const auto faces = mesh_->boundaryFaces();
    for (const auto& tl : tissue.tractions) {
      int count = 0;
      for (const auto& f : faces) {
        bool inside = true;
        for (int q : f.nodes) inside = inside && tl.region.contains(mesh_->node(q), tol);
        if (!inside) continue;
        ++count;
        addFaceTraction(*mesh_, f, tl.traction, f_ext_);
      }
      if (count == 0) throw InputError(file, tl.key + ".region", "contains no boundary face of the tissue");
    }
  }
  scene_f_ext_ = f_ext_;
  dofs_.gather(mass_, mass_free_);
  solver_ = std::make_unique<SystemSolver>(*model_, dofs_, settings_.linear);
  dv_free_.setZero(dofs_.numFree());
}

void TissueBody::accumulate(StepStats& s, const LinearSolveStats& l) const {
  s.assemble_ms += l.assemble_ms;
  s.factor_ms += l.factor_ms;
  s.solve_ms += l.solve_ms;
  s.linear_iterations += l.iterations;
  s.factorizations += l.refactored ? 1 : 0;
  s.linear_residual = std::max(s.linear_residual, l.relative_residual);
}

StepStats TissueBody::stepDynamic(double h) {
  StepStats st = freeMotion(h);
  commit(h);
  return st;
}

void TissueBody::commit(double h) {
  VecX dv;
  dofs_.scatter(dv_free_, dv);
  v_ += dv;  // prescribed entries of dv are zero and v stays zero there
  x_ += h * v_;
}

void TissueBody::cacheColumns(const std::vector<int>& free_dofs) const {
  const long version = solver_->factor().factorizations();
  std::vector<int> todo;
  std::vector<std::pair<long, int>> stale;
  for (int f : free_dofs) {
    auto it = columns_.find(f);
    if (it == columns_.end()) todo.push_back(f);
    else if (it->second.version != version) stale.emplace_back(it->second.version, f);
  }
  // Evict columns no longer in use once the cache is much larger than the working set.
  if (columns_.size() > 2 * free_dofs.size() + 64) {
    std::unordered_map<int, CachedColumn> kept;
    for (int f : free_dofs) {
      auto it = columns_.find(f);
      if (it != columns_.end()) kept.emplace(f, std::move(it->second));
    }
    columns_ = std::move(kept);
  }
  std::sort(stale.begin(), stale.end());
  for (size_t k = 0; k < stale.size() && k < static_cast<size_t>(kColumnRefresh); ++k) todo.push_back(stale[k].second);
  if (todo.empty()) return;
  Eigen::MatrixXd E = Eigen::MatrixXd::Zero(dofs_.numFree(), static_cast<Eigen::Index>(todo.size()));
  for (size_t j = 0; j < todo.size(); ++j) E(todo[j], static_cast<Eigen::Index>(j)) = 1.0;
  Eigen::MatrixXd X;
  solver_->factor().solve(E, X);
  for (size_t j = 0; j < todo.size(); ++j) columns_[todo[j]] = {X.col(static_cast<Eigen::Index>(j)), version};
}

const VecX& TissueBody::column(int f) const { return columns_.at(f).x; }

void TissueBody::complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C) const {
  cacheColumns(free_dofs);
  const auto k = static_cast<Eigen::Index>(free_dofs.size());
  C.resize(k, k);
  for (Eigen::Index j = 0; j < k; ++j) {
    const VecX& col = column(free_dofs[j]);
    for (Eigen::Index i = 0; i < k; ++i) C(i, j) = col[free_dofs[i]];
  }
  C = (0.5 * (C + C.transpose())).eval();
}

void TissueBody::addInverseColumns(const std::vector<int>& free_dofs, const VecX& c) {
  cacheColumns(free_dofs);
  for (size_t j = 0; j < free_dofs.size(); ++j)
    if (c[static_cast<Eigen::Index>(j)] != 0) dv_free_.noalias() += c[static_cast<Eigen::Index>(j)] * column(free_dofs[j]);
}

StepStats TissueBody::freeMotion(double h) {
  StepStats st;
  auto t0 = std::chrono::steady_clock::now();
  const double alpha = settings_.rayleigh_mass, beta = settings_.rayleigh_stiffness;
  model_->updateRotations(x_);
  VecX f = f_ext_;
  model_->addInternalForce(x_, f);
  // f - h K v - C v = f - (h + beta) K v - alpha M v
  model_->addStiffnessProduct(v_, -(h + beta), f);
  addSupportProduct(x_, 1.0, f);
  addSupportProduct(v_, h + beta, f);
  f.array() -= alpha * mass_.array() * v_.array();
  VecX b;
  dofs_.gather(f, b);
  b *= h;
  st.forces_ms = msSince(t0);

  const auto l = solver_->solve(mass_free_, 1 + h * alpha, h * beta + h * h, b, dv_free_);
  accumulate(st, l);
  return st;
}

namespace {
// Restores the solver's persistent extra stiffness (the support) and drops its factor when
// a solve with temporary blocks ends.
struct Detach {
  SystemSolver& s;
  const ElementBlocks* base;
  ~Detach() {
    s.setExtraStiffness(base);
    s.invalidate();
  }
};
}  // namespace

StepStats TissueBody::solveStatic() {
  return solveStatic(ExtraForce{}, settings_.static_tolerance, settings_.static_max_iterations);
}

// Full Newton steps under load control before falling back to backtracking (a safeguard
// against an active set that cycles).
constexpr int kFullControlledSteps = 20;

StepStats TissueBody::solveStatic(const ExtraForce& extra, double tol, int max_iterations, LoadControl* control) {
  StepStats st;
  VecX r_full, r, dx_free, dx, unit_free, w_free, w, grad_full, grad;
  ElementBlocks blocks;
  auto loadNorm = [&]() {
    VecX fe;
    dofs_.gather(f_ext_, fe);
    return fe.norm();
  };
  double ref = loadNorm(), rn0 = 0;
  Detach detach{*solver_, supportOrNull()};  // the solver must not keep `blocks` past this call
  // Residual (free DOFs) at the current x_, with the extra terms' blocks.
  auto residual = [&](VecX& out) {
    model_->updateRotations(x_);
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
  VecX x_trial, r_trial;
  double rn = 0, gw = 1;
  const double lin_tol = solver_->settings().tolerance;
  bool tight = true;  // the last correction was solved to the solver's own tolerance
  for (int it = 0; it <= max_iterations; ++it) {
    auto t0 = std::chrono::steady_clock::now();
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
    const bool small_step = it > 0 && dx.norm() <= tol * un;
    const bool balanced = rn <= tol * ref || ref == 0 || (small_step && tight);
    if (balanced && (!control || std::abs(c) <= control->tolerance)) {
      st.newton_iterations = it;
      v_.setZero();
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
    accumulate(st, solver_->solve(mass_free_, 0.0, 1.0, r, dx_free, eta));
    double ds = 0;
    if (control) {
      // w = K^-1 unit (warm-started from the last one: K changes little between steps), then
      // the scale change that satisfies the linearised constraint.
      accumulate(st, solver_->solve(mass_free_, 0.0, 1.0, unit_free, w_free, std::max(std::min(eta, 1e-3), lin_tol)));
      gw = grad.dot(w_free);
      if (!(gw > 0)) throw NumericalError(-1, "static solve: the controlled displacement does not grow with the load");
      ds = -(c + grad.dot(dx_free)) / gw;
      const double s = control->scale;
      ds = std::clamp(ds, s / control->max_growth - s, s * control->max_growth - s);
      dx_free += ds * w_free;
    }
    dofs_.scatter(dx_free, dx);
    t0 = std::chrono::steady_clock::now();
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

double TissueBody::kineticEnergy() const { return 0.5 * (mass_.array() * v_.array().square()).sum(); }

void TissueBody::setState(const VecX& x, const VecX& v) {
  for (int i = 0; i < dofs_.numFull(); ++i)
    if (!dofs_.prescribed(i)) {
      x_[i] = x[i];
      v_[i] = v[i];
    }
  dofs_.interpolateHanging(x_);
  dofs_.interpolateHanging(v_);
}

}  // namespace needle_sim

namespace needle_sim {
void TissueBody::setSupport(ElementBlocks blocks) {
  support_ = std::move(blocks);
  solver_->setExtraStiffness(supportOrNull());
  solver_->invalidate();
  columns_.clear();
}

void TissueBody::addSupportProduct(const VecX& y, double c, VecX& f) const {
  Eigen::Matrix<double, 24, 1> ye;
  for (size_t i = 0; i < support_.element.size(); ++i) {
    const auto& el = mesh_->element(support_.element[i]);
    for (int a = 0; a < 8; ++a) ye.segment<3>(3 * a) = node3(y, el[a]);
    const Eigen::Matrix<double, 24, 1> w = support_.K[i] * ye;
    for (int a = 0; a < 8; ++a) node3(f, el[a]) -= c * w.segment<3>(3 * a);
  }
}

void TissueBody::setPrescribedPositions(const VecX& x) {
  for (int i = 0; i < dofs_.numFull(); ++i)
    if (dofs_.prescribed(i)) x_[i] = x[i];
  dofs_.interpolateHanging(x_);
}
}  // namespace needle_sim
