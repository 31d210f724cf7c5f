#include "needle_sim/tissue/tissue_body.hpp"

#include <algorithm>
#include <cmath>
#include <iterator>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/tissue/tissue_loads.hpp"

namespace needle_sim {

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
      free_guess_(o.free_guess_),
      free_guess2_(o.free_guess2_),
      step_h_(o.step_h_),
      support_(o.support_),
      columns_(o.columns_) {
  model_ = std::make_unique<CorotationalHexModel>(*o.model_, *mesh_);
  solver_ = std::make_unique<SystemSolver>(*o.solver_, *model_, dofs_);
  solver_->setExtraStiffness(supportOrNull());
  if (o.static_factor_blocks_) solver_->invalidate();  // a kept static factor holds blocks the copy does not keep
}

TissueBody::TissueBody(HexMesh mesh, const TissueParameters& tissue, const SolverSettings& solver,
                       const std::string& source, const std::vector<std::vector<std::pair<int, double>>>& node_hanging)
    : mesh_(std::make_unique<HexMesh>(std::move(mesh))), settings_(solver) {
  model_ = std::make_unique<CorotationalHexModel>(*mesh_, tissue.material);
  const int n = mesh_->numNodes();
  rest_ = mesh_->restPositions();
  x_ = rest_;
  v_ = VecX::Zero(3 * n);
  const std::vector<char> prescribed = prescribeDirichlet(*mesh_, tissue.dirichlet, source, x_);
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
  const VecX& vol = model_->nodalVolume();
  mass_.resize(3 * n);
  for (int i = 0; i < n; ++i) mass_.segment<3>(3 * i).setConstant(tissue.material.density * vol[i]);
  f_ext_ = tissueLoads(*mesh_, vol, tissue, source);
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
  s.stale_fallbacks += l.budget_exhausted ? 1 : 0;
  s.async_factorizations += l.async_swapped ? 1 : 0;
  s.factor_waits += l.async_waited ? 1 : 0;
  s.factor_wait_ms += l.async_wait_ms;
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

void TissueBody::complianceBlock(const std::vector<int>& free_dofs, Eigen::MatrixXd& C) const {
  columns_.prepare(free_dofs, solver_->factor(), solver_->factorVersion(), dofs_.numFree());
  const auto k = static_cast<Eigen::Index>(free_dofs.size());
  C.resize(k, k);
  for (Eigen::Index j = 0; j < k; ++j) {
    const VecX& col = columns_.column(free_dofs[j]);
    for (Eigen::Index i = 0; i < k; ++i) C(i, j) = col[free_dofs[i]];
  }
  C = (0.5 * (C + C.transpose())).eval();
}

void TissueBody::addInverseColumns(const std::vector<int>& free_dofs, const VecX& c) {
  columns_.prepare(free_dofs, solver_->factor(), solver_->factorVersion(), dofs_.numFree());
  for (size_t j = 0; j < free_dofs.size(); ++j)
    if (c[static_cast<Eigen::Index>(j)] != 0)
      dv_free_.noalias() += c[static_cast<Eigen::Index>(j)] * columns_.column(free_dofs[j]);
}

StepStats TissueBody::freeMotion(double h) {
  StepStats st;
  if (step_h_ > 0 && h != step_h_) {
    // A new time step (a prediction at a coarser one): A = (1 + h alpha) M + (h beta + h^2) K
    // is another matrix. The factor of the old one would still precondition CG, but the
    // constraint solve takes the compliance from it and its cached columns: refactorise, and
    // drop the columns (not refreshed a few a step as after a rotation drift).
    solver_->invalidate();
    columns_.clear();
    free_guess_.resize(0);
    free_guess2_.resize(0);
  }
  step_h_ = h;
  const auto t0 = steadyNow();
  const double alpha = settings_.rayleigh_mass, beta = settings_.rayleigh_stiffness;
  // Lagged rotations (doc/method.md "Time integration"): the step's stiffness and forces take
  // the factor's rotations, so that its matrix is the factor's own (one CG iteration); the
  // rotations of the positions only decide when to refresh, and are what a refresh is made of.
  const double drift_limit = settings_.linear.rotation_drift;
  const bool lagged = drift_limit > 0 && settings_.linear.method == LinearSolverSettings::Method::Pcg;
  LinearSolveStats swapped;
  if (lagged) {
    solver_->setLaggedRotations(&rotations_now_);
    if (solver_->takeDueRefresh(swapped)) adoptRefreshColumns();
  }
  model_->updateRotations(x_);
  if (lagged && solver_->factorRotations().size() == model_->rotations().size()) {
    rotations_now_ = model_->rotations();
    const std::vector<Mat3>& held = solver_->factorRotations();
    // ||R - R0||_F = 2 sqrt(2) sin(angle / 2): compared without the arcsine.
    const double limit = 2.0 * std::sqrt(2.0) * std::sin(0.5 * drift_limit);
    double drift = 0;
    for (size_t e = 0; e < held.size(); ++e) drift = std::max(drift, (rotations_now_[e] - held[e]).norm());
    model_->setRotations(held);
    if (drift > limit) solver_->requestRefresh();
  }
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

  // CG starts from the free motion extrapolated from the last two steps', not from the last
  // total increment: in a steady insertion the constraint correction cancels most of the
  // free motion, so the total is near zero and a poor guess, while the free motion changes
  // smoothly. Gel steering scene: 3.6 CG iterations a step instead of 5.9, the same path to
  // 1e-10 m (doc/benchmarks.md "Bevel tip"); a quadratic extrapolation saved 0.2 more.
  if (free_guess_.size() == b.size()) {
    if (free_guess2_.size() == b.size()) dv_free_ = 2 * free_guess_ - free_guess2_;
    else dv_free_ = free_guess_;
  }
  // A background refresh also refreshes the cached compliance columns with its factor: at its
  // swap they are all current, instead of kRefresh a step recomputed here (on the DBS mesh
  // 8 solves, 2.4 ms a step, for ten steps after each swap).
  const auto l = solver_->solve(mass_free_, 1 + h * alpha, h * beta + h * h, b, dv_free_, 0,
                                [this] { return refreshColumnDofs(); });
  if (l.async_swapped) adoptRefreshColumns();
  free_guess2_ = free_guess_;
  free_guess_ = dv_free_;
  accumulate(st, l);
  accumulate(st, swapped);
  return st;
}

void TissueBody::adoptRefreshColumns() {
  std::vector<int> dofs;
  Eigen::MatrixXd X;
  long version = 0;
  if (solver_->takeRefreshColumns(dofs, X, version)) columns_.adopt(dofs, X, version);
}

StiffnessFactor& TissueBody::dualFactor() const {
  if (!dual_factor_) dual_factor_ = std::make_unique<StiffnessFactor>(*model_, dofs_, solver_->assembler(), settings_.linear.ordering);
  return *dual_factor_;
}

StiffnessFactor& TissueBody::backgroundStiffnessFactor() const {
  if (!background_dual_factor_)
    background_dual_factor_ = std::make_unique<StiffnessFactor>(*model_, dofs_, solver_->assembler(), settings_.linear.ordering);
  return *background_dual_factor_;
}

double TissueBody::kineticEnergy() const { return 0.5 * (mass_.array() * v_.array().square()).sum(); }

void TissueBody::prepareForSteps(double h, const std::vector<int>& elements) {
  model_->updateRotations(x_);
  solver_->factorNow(mass_free_, 1 + h * settings_.rayleigh_mass, h * settings_.rayleigh_stiffness + h * h);
  step_h_ = h;
  const std::vector<int> free = freeDofsOf(elements);
  if (!free.empty()) columns_.prepare(free, solver_->factor(), solver_->factorVersion(), dofs_.numFree());
}

std::vector<int> TissueBody::freeDofsOf(const std::vector<int>& elements) const {
  std::vector<int> free;
  std::vector<char> seen(dofs_.numFree(), 0);
  for (int e : elements)
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) {
        const int full = 3 * mesh_->element(e)[a] + d;
        for (const DofWeight* x = dofs_.expansionBegin(full); x != dofs_.expansionEnd(full); ++x)
          if (!seen[x->free]) {
            seen[x->free] = 1;
            free.push_back(x->free);
          }
      }
  return free;
}

std::vector<int> TissueBody::refreshColumnDofs() {
  std::vector<int> d = columns_.dofs();
  if (!elements_ahead_ || !settings_.linear.columns_ahead) return d;
  std::vector<int> ahead = freeDofsOf(elements_ahead_());
  std::sort(ahead.begin(), ahead.end());
  columns_.keep(ahead);
  std::vector<int> all;
  std::set_union(d.begin(), d.end(), ahead.begin(), ahead.end(), std::back_inserter(all));
  return all;
}

void TissueBody::setState(const VecX& x, const VecX& v) {
  for (int i = 0; i < dofs_.numFull(); ++i)
    if (!dofs_.prescribed(i)) {
      x_[i] = x[i];
      v_[i] = v[i];
    }
  dofs_.interpolateHanging(x_);
  dofs_.interpolateHanging(v_);
}

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
