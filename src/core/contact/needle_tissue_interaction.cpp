#include "needle_sim/contact/needle_tissue_interaction.hpp"

#include <cassert>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "needle_sim/contact/projected_gauss_seidel.hpp"
#include "needle_sim/contact/puncture_constraint.hpp"
#include "needle_sim/contact/shaft_constraint.hpp"
#include "needle_sim/contact/tip_constraint.hpp"
#include "needle_sim/core/error.hpp"

namespace needle_sim {

const char* toString(InsertionState s) {
  switch (s) {
    case InsertionState::Approaching: return "approaching";
    case InsertionState::InContact: return "in_contact";
    case InsertionState::Punctured: return "punctured";
    case InsertionState::Inserted: return "inserted";
    case InsertionState::Withdrawing: return "withdrawing";
    case InsertionState::Out: return "out";
  }
  return "?";
}

namespace {
// Frame with the given first column and an orthonormal completion.
Mat3 frameFrom(const Vec3& d0) {
  Mat3 F;
  F.col(0) = d0.normalized();
  F.col(1) = F.col(0).unitOrthogonal();
  F.col(2) = F.col(0).cross(F.col(1));
  return F;
}
}  // namespace

NeedleTissueInteraction::NeedleTissueInteraction(const InteractionSettings& s, TissueBody& tissue,
                                                 std::vector<NeedleBody*> needles, const EmbeddedSurface* organ)
    : settings_(s), needles_(std::move(needles)), tracks_(needles_.size()) {
  bindTissue(tissue, organ);
  for (size_t n = 0; n < needles_.size(); ++n) tracks_[n].sheathed = sheathOf(static_cast<int>(n)) >= 0;
}

NeedleTissueInteraction::NeedleTissueInteraction(const NeedleTissueInteraction& o, TissueBody& tissue,
                                                 std::vector<NeedleBody*> needles, const EmbeddedSurface* organ)
    : settings_(o.settings_), needles_(std::move(needles)), tracks_(o.tracks_) {
  assert(needles_.size() == o.needles_.size());
  assert(tissue.mesh().numNodes() == o.tissue_->mesh().numNodes());
  bindTissue(tissue, organ);
  constraints_.reserve(o.constraints_.size());
  for (const auto& c : o.constraints_) constraints_.push_back(c->clone());
}

void NeedleTissueInteraction::bindTissue(TissueBody& tissue, const EmbeddedSurface* organ) {
  tissue_ = &tissue;
  const HexMesh& mesh = tissue.mesh();
  surface_ = organ ? std::make_unique<TissueSurface>(mesh, *organ) : std::make_unique<TissueSurface>(mesh);
  rest_locator_ = std::make_unique<PointLocator>(mesh);
  column_of_.assign(tissue.dofs().numFree(), -1);
  node_elements_.assign(mesh.numNodes(), {});
  for (int e = 0; e < mesh.numElements(); ++e)
    for (int a : mesh.element(e)) node_elements_[a].push_back(e);
}

void NeedleTissueInteraction::rebind(TissueBody& tissue, const EmbeddedSurface* organ) {
  bindTissue(tissue, organ);
  // Constraint points are material points: found again by their rest position (a point of
  // an immersed surface may lie a rounding error outside the cells: the nearest is taken).
  for (auto& c : constraints_) {
    EmbeddedPoint ep;
    if (!rest_locator_->locate(c->tissue.rest, ep) && !rest_locator_->locateNearest(c->tissue.rest, ep))
      throw std::logic_error("re-embedding a constraint point: rest position outside the new mesh");
    c->tissue = ep;
  }
}

int NeedleTissueInteraction::activePoints(int n) const {
  int k = 0;
  for (const auto& c : constraints_) k += c->needle == n;
  return k;
}

Vec3 NeedleTissueInteraction::forceOnNeedle(int n) const {
  Vec3 f = Vec3::Zero();
  for (const auto& c : constraints_) {
    if (c->needle != n) continue;
    int e;
    double xi;
    Vec3 p, axis;
    needlePoint(n, c->s, e, xi, p, axis);
    const Vec3 fc = c->frame * c->lambda;
    const double x2 = xi * xi, x3 = x2 * xi;
    f += (2 * x3 - 3 * x2 + 1) * fc + (-2 * x3 + 3 * x2) * fc;  // translational Hermite weights of nodes e, e + 1
  }
  return f;
}

Vec3 NeedleTissueInteraction::forceOnTissue() const {
  Vec3 f = Vec3::Zero();
  for (const auto& c : constraints_) {
    const Vec3 fc = c->frame * c->lambda;
    for (int a = 0; a < 8; ++a) f -= c->tissue.weights[a] * fc;
  }
  return f;
}

// The needle centre line between two nodes is the cubic Hermite curve of the beam element
// (end positions and end tangents from the node orientations), so shaft points between
// nodes see the needle's curvature; its velocity involves the nodes' spins (hermiteRow).
void NeedleTissueInteraction::needlePoint(int n, double s, int& e, double& xi, Vec3& p, Vec3& axis) const {
  const NeedleBody& nd = *needles_[n];
  const double L0 = nd.beam().elementLength();
  const int ne = nd.beam().numElements();
  e = std::clamp(static_cast<int>(std::floor(s / L0)), 0, ne - 1);
  xi = std::clamp(s / L0 - e, 0.0, 1.0);
  const Vec3& a = nd.state().p[e];
  const Vec3& b = nd.state().p[e + 1];
  const double l = (b - a).norm();
  const Vec3 ta = nd.state().q[e] * nd.beam().restDirection();
  const Vec3 tb = nd.state().q[e + 1] * nd.beam().restDirection();
  const double x2 = xi * xi, x3 = x2 * xi;
  p = (2 * x3 - 3 * x2 + 1) * a + (x3 - 2 * x2 + xi) * l * ta + (-2 * x3 + 3 * x2) * b + (x3 - x2) * l * tb;
  const Vec3 dp = (6 * x2 - 6 * xi) * a + (3 * x2 - 4 * xi + 1) * l * ta + (-6 * x2 + 6 * xi) * b + (3 * x2 - 2 * xi) * l * tb;
  axis = dp.normalized();
}

double NeedleTissueInteraction::closestArcLength(int n, const Vec3& p) const {
  const NeedleBody& nd = *needles_[n];
  const double L0 = nd.beam().elementLength();
  double best = std::numeric_limits<double>::infinity(), s = 0;
  for (int e = 0; e < nd.beam().numElements(); ++e) {
    const Vec3& a = nd.state().p[e];
    const Vec3 d = nd.state().p[e + 1] - a;
    // Clamped to the segment, except beyond the tip, so that points the needle has been
    // withdrawn past get s > L.
    double t = std::max(0.0, d.dot(p - a) / d.squaredNorm());
    if (e + 1 < nd.beam().numElements()) t = std::min(t, 1.0);
    const double dist = (a + t * d - p).squaredNorm();
    if (dist < best) {
      best = dist;
      s = (e + t) * L0;
    }
  }
  return s;
}

bool NeedleTissueInteraction::locateCurrent(const Vec3& p, int hint, EmbeddedPoint& out) const {
  const HexMesh& mesh = tissue_->mesh();
  const VecX& x = tissue_->positions();
  auto tryElement = [&](int e) {
    Eigen::Matrix<double, 8, 3> X;
    for (int a = 0; a < 8; ++a) X.row(a) = node3(x, mesh.element(e)[a]).transpose();
    Vec3 xi;
    if (!hex8::inverseMap(X, p, xi) || xi.cwiseAbs().maxCoeff() > 1 + 1e-9) return false;
    out.element = e;
    out.xi = xi.cwiseMax(-1.0).cwiseMin(1.0);
    out.weights = hex8::shape(out.xi);
    out.rest = mesh.elementCorners(e).transpose() * out.weights;
    return true;
  };
  if (hint >= 0) {
    if (tryElement(hint)) return true;
    for (int a : mesh.element(hint))
      for (int e : node_elements_[a])
        if (e != hint && tryElement(e)) return true;
  }
  for (int e = 0; e < mesh.numElements(); ++e)
    if (tryElement(e)) return true;
  return false;
}

int NeedleTissueInteraction::sheathOf(int n) const {
  const Vec3 tip = needles_[n]->tipPosition();
  for (size_t m = 0; m < needles_.size(); ++m) {
    if (static_cast<int>(m) == n) continue;
    const auto& sec = needles_[m]->beam().section();
    if (!(sec.inner_radius > 0) || sec.inner_radius < needles_[n]->beam().section().outer_radius * (1 - 1e-9)) continue;
    const double L = needles_[m]->beam().length();
    const double s = closestArcLength(static_cast<int>(m), tip);
    if (s <= 0 || s > L + 1e-3 * settings_.shaft_spacing) continue;
    int e;
    double xi;
    Vec3 p, axis;
    needlePoint(static_cast<int>(m), std::min(s, L), e, xi, p, axis);
    if ((tip - p - axis * axis.dot(tip - p)).norm() <= sec.inner_radius) return static_cast<int>(m);
  }
  return -1;
}

// Lays shaft points every shaft_spacing along the cut path (in rest space) up to `upto`.
void NeedleTissueInteraction::layShaftPoints(int n, const EmbeddedPoint& upto,
                                             std::vector<std::unique_ptr<ContactConstraint>>& out) {
  Track& tr = tracks_[n];
  const double sp = settings_.shaft_spacing;
  for (int guard = 0; guard < 100000; ++guard) {
    const Vec3 d = upto.rest - tr.next_shaft_rest;
    const double len = d.norm();
    if (len < sp) break;
    EmbeddedPoint ep;
    if (rest_locator_->locate(tr.next_shaft_rest, ep)) {
      auto c = std::make_unique<ShaftConstraint>(settings_.friction);
      c->tissue = ep;
      c->needle = n;
      out.push_back(std::move(c));
    }
    tr.next_shaft_rest += d * (sp / len);
  }
}

void NeedleTissueInteraction::updateGeometry() {
  const HexMesh& mesh = tissue_->mesh();
  const VecX& x = tissue_->positions();
  std::vector<std::unique_ptr<ContactConstraint>> kept;
  for (auto& c : constraints_) {
    const NeedleBody& nd = *needles_[c->needle];
    const double L = nd.beam().length();
    if (c->kind() == ConstraintKind::Shaft) {
      const Vec3 pT = c->tissue.interpolate(mesh, x);
      c->s = closestArcLength(c->needle, pT);
      if (c->s >= L) {
        // The needle has been withdrawn past it: pass it to another needle running through
        // it (the electrode left by the cannula), or release it.
        int to = -1;
        for (size_t m = 0; m < needles_.size() && to < 0; ++m) {
          if (static_cast<int>(m) == c->needle) continue;
          const double sm = closestArcLength(static_cast<int>(m), pT);
          if (sm <= 0 || sm >= needles_[m]->beam().length()) continue;
          int e;
          double xi;
          Vec3 p, axis;
          needlePoint(static_cast<int>(m), sm, e, xi, p, axis);
          const double reach = nd.beam().section().outer_radius + needles_[m]->beam().section().outer_radius;
          if ((pT - p - axis * axis.dot(pT - p)).norm() <= reach) {
            to = static_cast<int>(m);
            c->s = sm;
          }
        }
        if (to < 0) continue;
        c->needle = to;
        c->lambda.setZero();
        if (tracks_[to].state == InsertionState::Approaching || tracks_[to].state == InsertionState::Out)
          tracks_[to].state = InsertionState::Inserted;
        tracks_[to].has_path = true;
      }
    } else {
      c->s = L;
    }
    if (c->kind() == ConstraintKind::Puncture) {
      // The contact point is the surface point on the needle axis at the tip: it moves with
      // the tip when the tip slides (the friction law acts on velocities), so that the tip is
      // tied where it is when it punctures.
      const int tip = nd.beam().numNodes() - 1;
      const Vec3 p = nd.state().p[tip];
      const Vec3 axis = (p - nd.state().p[tip - 1]).normalized();
      const double r = 0.5 * settings_.shaft_spacing + std::abs(c->gap[0]);
      SurfaceHit hit;
      if (surface_->firstEntry(x, p - axis * r, p + axis * r, hit)) {
        c->tissue = hit.material;
        c->frame = frameFrom(hit.normal);
      }
    }
    const Vec3 pT = c->tissue.interpolate(mesh, x);
    int e;
    double xi;
    Vec3 pN, axis;
    needlePoint(c->needle, c->s, e, xi, pN, axis);
    if (c->kind() != ConstraintKind::Puncture) c->frame = frameFrom(axis);
    c->gap = c->frame.transpose() * (pN - pT);
    kept.push_back(std::move(c));
  }
  constraints_ = std::move(kept);
}

InteractionStats NeedleTissueInteraction::solve(double h) {
  const auto t0 = std::chrono::steady_clock::now();
  InteractionStats st;
  const HexMesh& mesh = tissue_->mesh();
  const VecX& xT = tissue_->positions();

  // 1. Contact detection for needles not in the tissue.
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    if (tr.state != InsertionState::Approaching && tr.state != InsertionState::Out) continue;
    if (tr.sheathed) continue;  // inside another needle: it meets no tissue
    const NeedleBody& nd = *needles_[n];
    const int tip = nd.beam().numNodes() - 1;
    const Vec3 p = nd.state().p[tip];
    const Vec3 v = nd.velocities().segment<3>(6 * tip) + nd.velocityChange().segment<3>(6 * tip);
    const Vec3 axis = (p - nd.state().p[tip - 1]).normalized();
    if (v.dot(axis) <= 0) continue;  // only a needle moving forward can meet the surface
    const double reach = h * v.norm() + 1e-9;
    SurfaceHit hit;
    if (!surface_->firstEntry(xT, p - axis * reach, p + axis * (reach + std::max(0.0, h * v.dot(axis))), hit)) continue;
    auto c = std::make_unique<PunctureConstraint>(settings_.friction);
    c->tissue = hit.material;
    c->needle = static_cast<int>(n);
    c->frame = frameFrom(hit.normal);
    constraints_.push_back(std::move(c));
    tr.state = InsertionState::InContact;
  }
  updateGeometry();
  st.points = static_cast<int>(constraints_.size());
  if (constraints_.empty()) {
    st.ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    return st;
  }

  // 2. Rows: touched tissue DOFs (columns of the compliance) and needle DOFs.
  const int np = st.points, m = 3 * np;
  const DofMap& tdofs = tissue_->dofs();
  std::vector<int> tcols;  // free tissue DOFs touched
  std::vector<std::vector<int>> ncols(needles_.size());
  std::vector<std::vector<int>> ncol_of(needles_.size());
  for (size_t n = 0; n < needles_.size(); ++n) ncol_of[n].assign(needles_[n]->dofs().numFree(), -1);
  struct RowGeom {
    int e;
    double xi;
  };
  std::vector<RowGeom> geom(np);
  for (int p = 0; p < np; ++p) {
    const auto& c = *constraints_[p];
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) {
        if (std::abs(c.tissue.weights[a]) < 1e-12) continue;  // e.g. a point on an element edge
        const int full = 3 * mesh.element(c.tissue.element)[a] + d;
        for (const DofWeight* x = tdofs.expansionBegin(full); x != tdofs.expansionEnd(full); ++x)
          if (column_of_[x->free] < 0) {
            column_of_[x->free] = static_cast<int>(tcols.size());
            tcols.push_back(x->free);
          }
      }
    Vec3 pN, axis;
    needlePoint(c.needle, c.s, geom[p].e, geom[p].xi, pN, axis);
    const DofMap& nd = needles_[c.needle]->dofs();
    for (int node : {geom[p].e, geom[p].e + 1})
      for (int d = 0; d < 6; ++d) {
        const int f = nd.freeIndex(6 * node + d);
        if (f >= 0 && ncol_of[c.needle][f] < 0) {
          ncol_of[c.needle][f] = static_cast<int>(ncols[c.needle].size());
          ncols[c.needle].push_back(f);
        }
      }
  }
  // H restricted to the touched DOFs, one block per body.
  Eigen::MatrixXd HT = Eigen::MatrixXd::Zero(m, static_cast<Eigen::Index>(tcols.size()));
  std::vector<Eigen::MatrixXd> HN(needles_.size());
  for (size_t n = 0; n < needles_.size(); ++n) HN[n] = Eigen::MatrixXd::Zero(m, static_cast<Eigen::Index>(ncols[n].size()));
  for (int p = 0; p < np; ++p) {
    const auto& c = *constraints_[p];
    for (int k = 0; k < 3; ++k) {
      const Vec3 d = c.frame.col(k);
      for (int a = 0; a < 8; ++a)
        for (int j = 0; j < 3; ++j) {
          if (std::abs(c.tissue.weights[a]) < 1e-12) continue;
          const int full = 3 * mesh.element(c.tissue.element)[a] + j;
          for (const DofWeight* x = tdofs.expansionBegin(full); x != tdofs.expansionEnd(full); ++x)
            HT(3 * p + k, column_of_[x->free]) -= c.tissue.weights[a] * x->weight * d[j];
        }
      const DofMap& nd = needles_[c.needle]->dofs();
      // Hermite weights: d . v = h00 d.v_a + h10 l (t_a x d).w_a + h01 d.v_b + h11 l (t_b x d).w_b
      const double xi = geom[p].xi, x2 = xi * xi, x3 = x2 * xi;
      const NeedleBody& body = *needles_[c.needle];
      const int ea = geom[p].e;
      const double l = (body.state().p[ea + 1] - body.state().p[ea]).norm();
      const double wt[2] = {2 * x3 - 3 * x2 + 1, -2 * x3 + 3 * x2};
      const double wr[2] = {(x3 - 2 * x2 + xi) * l, (x3 - x2) * l};
      for (int q = 0; q < 2; ++q) {
        const Vec3 rot = (body.state().q[ea + q] * body.beam().restDirection()).cross(d) * wr[q];
        for (int j = 0; j < 3; ++j) {
          const int ft = nd.freeIndex(6 * (ea + q) + j), fr = nd.freeIndex(6 * (ea + q) + 3 + j);
          if (ft >= 0) HN[c.needle](3 * p + k, ncol_of[c.needle][ft]) += wt[q] * d[j];
          if (fr >= 0) HN[c.needle](3 * p + k, ncol_of[c.needle][fr]) += rot[j];
        }
      }
    }
  }

  // 3. Compliance from each body's factor; free velocities of the rows.
  Eigen::MatrixXd C, W = Eigen::MatrixXd::Zero(m, m);
  if (!tcols.empty()) {
    tissue_->complianceBlock(tcols, C);
    W.noalias() += HT * (C * HT.transpose());
  }
  for (size_t n = 0; n < needles_.size(); ++n) {
    if (ncols[n].empty()) continue;
    needles_[n]->complianceBlock(ncols[n], C);
    W.noalias() += HN[n] * (C * HN[n].transpose());
  }
  W *= h;
  VecX u_free = VecX::Zero(m);
  {
    VecX vT(tcols.size());
    const VecX& v = tissue_->velocities();
    const VecX& dv = tissue_->velocityChangeFree();
    for (size_t i = 0; i < tcols.size(); ++i) vT[static_cast<Eigen::Index>(i)] = v[tdofs.freeToFull()[tcols[i]]] + dv[tcols[i]];
    u_free += HT * vT;
    for (size_t n = 0; n < needles_.size(); ++n) {
      if (ncols[n].empty()) continue;
      const DofMap& nd = needles_[n]->dofs();
      VecX vN(ncols[n].size());
      for (size_t i = 0; i < ncols[n].size(); ++i) {
        const int full = nd.freeToFull()[ncols[n][i]];
        vN[static_cast<Eigen::Index>(i)] = needles_[n]->velocities()[full] + needles_[n]->velocityChange()[full];
      }
      u_free += HN[n] * vN;
    }
    // Rows' dependence on the prescribed needle base (moving with the command).
    for (int p = 0; p < np; ++p) {
      const auto& c = *constraints_[p];
      if (geom[p].e != 0) continue;
      const NeedleBody& nd = *needles_[c.needle];
      const Vec3 vb = nd.velocities().head<3>() + nd.velocityChange().head<3>();
      const Vec3 wb = nd.velocities().segment<3>(3) + nd.velocityChange().segment<3>(3);
      const double xi = geom[p].xi, x2 = xi * xi, x3 = x2 * xi;
      const double l = (nd.state().p[1] - nd.state().p[0]).norm();
      const Vec3 vpoint = (2 * x3 - 3 * x2 + 1) * vb +
                          (x3 - 2 * x2 + xi) * l * wb.cross(nd.state().q[0] * nd.beam().restDirection());
      u_free.segment<3>(3 * p) += c.frame.transpose() * vpoint;
    }
  }

  // A tiny compliance on every row (1e-8 of the largest diagonal entry) keeps W positive
  // definite when shaft points closer together than the nodes make rows redundant.
  {
    const double eps = 1e-8 * W.diagonal().maxCoeff();
    W.diagonal().array() += eps;
  }
  // 4. Projected Gauss-Seidel, warm-started from the last multipliers.
  std::vector<ContactConstraint*> cs;
  VecX lambda(m);
  for (int p = 0; p < np; ++p) {
    cs.push_back(constraints_[p].get());
    lambda.segment<3>(3 * p) = constraints_[p]->lambda;
  }
  // Force scale for the convergence test: the interaction's strengths (or 1 mN).
  const double force_scale = std::max({settings_.puncture_force, settings_.cutting_force, 1e-3});
  const PgsResult r =
      projectedGaussSeidel(W, u_free, cs, h, settings_.tolerance, settings_.max_iterations, force_scale, lambda);
  st.iterations = r.iterations;
  st.residual = r.residual;
  st.converged = r.converged;
  if (!lambda.allFinite()) throw NumericalError(-1, "constraint solve produced NaN/Inf");
  for (int p = 0; p < np; ++p) constraints_[p]->lambda = lambda.segment<3>(3 * p);

  // 5. Corrections dv = h A^-1 H^T lambda for each body.
  if (!tcols.empty()) tissue_->addInverseColumns(tcols, h * (HT.transpose() * lambda));
  for (size_t n = 0; n < needles_.size(); ++n)
    if (!ncols[n].empty()) needles_[n]->addInverseColumns(ncols[n], h * (HN[n].transpose() * lambda));
  for (int f : tcols) column_of_[f] = -1;
  st.ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return st;
}

void NeedleTissueInteraction::afterCommit() {
  const HexMesh& mesh = tissue_->mesh();
  const VecX& x = tissue_->positions();
  std::vector<std::unique_ptr<ContactConstraint>> created;
  for (auto it = constraints_.begin(); it != constraints_.end();) {
    ContactConstraint& c = **it;
    Track& tr = tracks_[c.needle];
    const NeedleBody& nd = *needles_[c.needle];
    const Vec3 tip = nd.tipPosition();
    const Vec3 pT = c.tissue.interpolate(mesh, x);
    if (c.kind() == ConstraintKind::Puncture) {
      const double gap = c.frame.col(0).dot(tip - pT);
      if (c.lambda[0] > settings_.puncture_force) {
        // Puncture: the tip is tied to the tissue where it touched; the path starts there.
        tr.puncture_force = c.lambda[0];
        auto t = std::make_unique<TipConstraint>(settings_.friction, settings_.cutting_force);
        t->tissue = c.tissue;
        t->needle = c.needle;
        tr.next_shaft_rest = c.tissue.rest;
        tr.has_path = true;
        tr.state = InsertionState::Punctured;
        created.push_back(std::move(t));
        it = constraints_.erase(it);
        continue;
      }
      if (c.lambda[0] <= 0 && gap > 0) {  // lifted off
        tr.state = tr.has_path ? InsertionState::Out : InsertionState::Approaching;
        it = constraints_.erase(it);
        continue;
      }
    } else if (c.kind() == ConstraintKind::Tip) {
      const Vec3 axis = (tip - nd.state().p[nd.beam().numNodes() - 2]).normalized();
      const double advance = axis.dot(tip - pT);
      auto& tipc = static_cast<TipConstraint&>(c);
      if (tipc.cutting() && advance > 0) {
        // Cutting: the anchor moves to the tissue point now at the tip; the path behind it
        // gets its shaft points.
        EmbeddedPoint anchor;
        if (locateCurrent(tip, c.tissue.element, anchor)) {
          layShaftPoints(c.needle, anchor, created);
          c.tissue = anchor;
          tr.state = InsertionState::Inserted;
        } else {
          // The tip left the tissue mesh (through the far side): keep the path, drop the tip.
          layShaftPoints(c.needle, c.tissue, created);
          it = constraints_.erase(it);
          continue;
        }
      } else if (advance < -1e-3 * settings_.shaft_spacing) {
        // Pulled back: the tip slides out of its channel; only the shaft points hold it.
        tr.state = InsertionState::Withdrawing;
        it = constraints_.erase(it);
        continue;
      } else if (tr.state == InsertionState::Punctured) {
        tr.state = InsertionState::Inserted;
      }
    }
    ++it;
  }
  // A needle whose tip comes out of its sheath inside the tissue is tied there.
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    const bool sheathed = sheathOf(static_cast<int>(n)) >= 0;
    if (tr.sheathed && !sheathed && (tr.state == InsertionState::Approaching || tr.state == InsertionState::Out ||
                                     tr.state == InsertionState::Inserted)) {
      bool has_tip = false;
      for (const auto& c : constraints_) has_tip |= c->needle == static_cast<int>(n) && c->kind() == ConstraintKind::Tip;
      EmbeddedPoint anchor;
      if (!has_tip && locateCurrent(needles_[n]->tipPosition(), -1, anchor)) {
        auto t = std::make_unique<TipConstraint>(settings_.friction, settings_.cutting_force);
        t->tissue = anchor;
        t->needle = static_cast<int>(n);
        created.push_back(std::move(t));
        tr.state = InsertionState::Inserted;
        tr.has_path = true;
        tr.next_shaft_rest = anchor.rest;
      }
    }
    tr.sheathed = sheathed;
  }
  for (auto& c : created) constraints_.push_back(std::move(c));
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    if (tr.has_path && activePoints(static_cast<int>(n)) == 0 &&
        (tr.state == InsertionState::Withdrawing || tr.state == InsertionState::Inserted))
      tr.state = InsertionState::Out;
  }
}

}  // namespace needle_sim
