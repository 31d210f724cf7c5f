#include "needle_sim/contact/needle_tissue_interaction.hpp"

#include <cassert>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "needle_sim/contact/centre_line.hpp"
#include "needle_sim/contact/interface_compliance.hpp"
#include "needle_sim/contact/constraint_solve.hpp"
#include "needle_sim/contact/puncture_constraint.hpp"
#include "needle_sim/contact/shaft_constraint.hpp"
#include "needle_sim/contact/sheath.hpp"
#include "needle_sim/contact/tip_constraint.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/core/stopwatch.hpp"

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
  bindTissue(tissue, TissueBinding::make(tissue.mesh(), organ));
  for (size_t n = 0; n < needles_.size(); ++n)
    tracks_[n].sheathed = sheathOf(needles_, static_cast<int>(n), 1e-3 * settings_.shaft_spacing) >= 0;
}

NeedleTissueInteraction::NeedleTissueInteraction(const NeedleTissueInteraction& o, TissueBody& tissue,
                                                 std::vector<NeedleBody*> needles, const EmbeddedSurface* organ)
    : settings_(o.settings_), needles_(std::move(needles)), tracks_(o.tracks_) {
  assert(needles_.size() == o.needles_.size());
  assert(tissue.mesh().numNodes() == o.tissue_->mesh().numNodes());
  bindTissue(tissue, TissueBinding::make(tissue.mesh(), organ));
  constraints_.reserve(o.constraints_.size());
  for (const auto& c : o.constraints_) constraints_.push_back(c->clone());
}

TissueBinding TissueBinding::make(const HexMesh& mesh, const EmbeddedSurface* organ) {
  TissueBinding b;
  b.surface = organ ? std::make_unique<TissueSurface>(mesh, *organ) : std::make_unique<TissueSurface>(mesh);
  b.locator = std::make_unique<PointLocator>(mesh);
  b.node_elements.assign(mesh.numNodes(), {});
  for (int e = 0; e < mesh.numElements(); ++e)
    for (int a : mesh.element(e)) b.node_elements[a].push_back(e);
  return b;
}

void NeedleTissueInteraction::bindTissue(TissueBody& tissue, TissueBinding binding) {
  tissue_ = &tissue;
  surface_ = std::move(binding.surface);
  rest_locator_ = std::move(binding.locator);
  node_elements_ = std::move(binding.node_elements);
  column_of_.assign(tissue.dofs().numFree(), -1);
  tissue.setElementsAhead([this] { return elementsAhead(); });
}

void NeedleTissueInteraction::rebind(TissueBody& tissue, const EmbeddedSurface* organ) {
  rebind(tissue, TissueBinding::make(tissue.mesh(), organ));
}

void NeedleTissueInteraction::rebind(TissueBody& tissue, TissueBinding binding) {
  bindTissue(tissue, std::move(binding));
  // Constraint points are material points: found again by their rest position (a point of
  // an immersed surface may lie a rounding error outside the cells: the nearest is taken).
  for (auto& c : constraints_) {
    EmbeddedPoint ep;
    if (!rest_locator_->locate(c->tissue.rest, ep) && !rest_locator_->locateNearest(c->tissue.rest, ep))
      throw std::logic_error("re-embedding a constraint point: rest position outside the new mesh");
    c->tissue = ep;
  }
  for (Track& tr : tracks_)
    if (tr.has_end) {
      EmbeddedPoint ep;
      if (rest_locator_->locate(tr.path_end.rest, ep) || rest_locator_->locateNearest(tr.path_end.rest, ep)) tr.path_end = ep;
      else tr.has_end = false;
    }
}

std::unique_ptr<TipConstraint> NeedleTissueInteraction::makeTip(int n) const {
  const BevelParameters& b = needles_[n]->bevel();
  const double lateral = b.enabled ? b.lateral_ratio * settings_.cutting_force : 0.0;
  auto t = std::make_unique<TipConstraint>(settings_.friction, settings_.cutting_force, lateral);
  t->needle = n;
  return t;
}

void NeedleTissueInteraction::extendPath(int n, const Vec3& rest) {
  // A point every quarter shaft spacing: enough to fit the path's curvature, few enough to
  // publish.
  std::vector<Vec3>& path = tracks_[n].path;
  if (path.empty() || (rest - path.back()).norm() >= 0.25 * settings_.shaft_spacing) path.push_back(rest);
}

void NeedleTissueInteraction::cutPathNow(int n, std::vector<Vec3>& out) const {
  out.clear();
  const HexMesh& mesh = tissue_->mesh();
  const VecX& x = tissue_->positions();
  for (const Vec3& r : tracks_[n].path) {
    EmbeddedPoint ep;
    if (rest_locator_->locate(r, ep) || rest_locator_->locateNearest(r, ep)) out.push_back(ep.interpolate(mesh, x));
  }
}

void NeedleTissueInteraction::setValues(const InteractionSettings& s) {
  settings_.puncture_force = s.puncture_force;
  settings_.cutting_force = s.cutting_force;
  settings_.friction = s.friction;
  settings_.grip_pressure = s.grip_pressure;
  for (const auto& c : constraints_) {
    switch (c->kind()) {
      case ConstraintKind::Tip: {
        const BevelParameters& b = needles_[c->needle]->bevel();
        static_cast<TipConstraint&>(*c).setForces(settings_.friction, settings_.cutting_force,
                                                  b.enabled ? b.lateral_ratio * settings_.cutting_force : 0.0);
        break;
      }
      case ConstraintKind::Shaft:
        static_cast<ShaftConstraint&>(*c).setFriction(settings_.friction);
        static_cast<ShaftConstraint&>(*c).setGrip(grip(c->needle));
        break;
      case ConstraintKind::Puncture:
        static_cast<PunctureConstraint&>(*c).setFriction(settings_.friction);
        break;
    }
  }
}

double NeedleTissueInteraction::grip(int n) const {
  // The normal force of the radial pressure over one shaft point's share of the path.
  return 2 * M_PI * needles_[n]->beam().section().outer_radius * settings_.grip_pressure * settings_.shaft_spacing;
}

double NeedleTissueInteraction::interfaceCompliance(int n, int e) const {
  using Mode = InteractionSettings::LateralStiffness;
  double k = settings_.lateral_stiffness;
  if (settings_.lateral_mode == Mode::Rigid) return 0;
  if (settings_.lateral_mode == Mode::Auto) {
    const Eigen::Matrix<double, 8, 3> c = tissue_->mesh().elementCorners(e);
    const double edge = (c.colwise().maxCoeff() - c.colwise().minCoeff()).mean();
    const LinearElasticMaterial m = tissue_->model().materialInUse();
    const double r = needles_[n]->beam().section().outer_radius;
    k = nearFieldLateralStiffness(m.young, m.poisson, r, resolvedRadius(edge, r));
  }
  return std::isfinite(k) ? 1 / (k * settings_.shaft_spacing) : 0.0;
}

double NeedleTissueInteraction::withdrawnSinceRelease(int needle) const {
  const Track& tr = tracks_[needle];
  if (tr.state != InsertionState::Withdrawing) return 0.0;
  const NeedleBody& nd = *needles_[needle];
  const Vec3 axis = (nd.state().p[1] - nd.state().p[0]).normalized();
  return (tr.release_base - nd.state().p[0]).dot(axis);
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
    const HermiteWeights h = hermite(centreLinePoint(*needles_[n], c->s).xi);
    f += (h.h00 + h.h01) * (c->frame * c->lambda);  // translational weights of the element's two nodes
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

// Lays shaft points every shaft_spacing along the cut path (in rest space) up to `upto`.
void NeedleTissueInteraction::layShaftPoints(int n, const EmbeddedPoint& upto,
                                             std::vector<std::unique_ptr<ContactConstraint>>& out) {
  Track& tr = tracks_[n];
  const double sp = settings_.shaft_spacing;
  const NeedleBody& nd = *needles_[n];
  auto lay = [&](const EmbeddedPoint& ep) {
    auto c = std::make_unique<ShaftConstraint>(settings_.friction, grip(n));
    c->tissue = ep;
    c->needle = n;
    out.push_back(std::move(c));
  };
  if (nd.bevel().enabled) {
    // A bevel needle bends under its tip load, so the path its tip cut is not where its
    // centre line lies now: the tissue closes on the needle where it is (the material point
    // at the centre line, `behind` the tip), its compliant tie unstretched. A point is laid
    // as soon as the tip has cut past its place: the needle's free length behind the tip is
    // below one spacing (doc/method.md "Bevel tip").
    for (int guard = 0; guard < 100000 && tr.cut_length >= tr.next_shaft_at; ++guard) {
      const double behind = tr.cut_length - tr.next_shaft_at;
      EmbeddedPoint ep;
      if (locateCurrent(centreLinePoint(nd, nd.beam().length() - behind).position, upto.element, ep)) lay(ep);
      tr.next_shaft_at += sp;
    }
    return;
  }
  for (int guard = 0; guard < 100000; ++guard) {
    const Vec3 d = upto.rest - tr.next_shaft_rest;
    const double len = d.norm();
    if (len < sp) break;
    EmbeddedPoint ep;
    if (rest_locator_->locate(tr.next_shaft_rest, ep)) lay(ep);
    tr.next_shaft_rest += d * (sp / len);
  }
}

bool NeedleTissueInteraction::updateGeometry() {
  bool lost = false;
  const HexMesh& mesh = tissue_->mesh();
  const VecX& x = tissue_->positions();
  std::vector<std::unique_ptr<ContactConstraint>> kept;
  for (auto& c : constraints_) {
    const NeedleBody& nd = *needles_[c->needle];
    const double L = nd.beam().length();
    if (c->kind() == ConstraintKind::Shaft) {
      const Vec3 pT = c->tissue.interpolate(mesh, x);
      c->s = closestArcLength(nd, pT);
      if (c->s >= L) {
        // The needle has been withdrawn past it: pass it to another needle running through
        // it (the electrode left by the cannula), or release it.
        double sm = 0;
        const int to = needleThrough(needles_, c->needle, pT, sm);
        if (to < 0) continue;
        c->needle = to;
        c->s = sm;
        static_cast<ShaftConstraint&>(*c).setGrip(grip(to));
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
      // Along the axis; for a tilted or buckled tip whose axis misses the surface nearby,
      // along the contact normal through the tip (the surface point under a sliding tip).
      const Vec3 n = c->frame.col(0);
      SurfaceHit hit, under;
      bool found = surface_->firstEntry(x, p - axis * r, p + axis * r, hit);
      // A tip that slid past a box's edge onto the next face stays on that face while the
      // face is under it: the axis, tilted back over the edge, also enters the face the tip
      // left, behind the tip. Taking that one made the contact chatter between the two faces
      // (the tip pushed back out of the one, released by the other) until the tip fell into
      // the tissue unpunctured (Interaction.ABuckledTipSlidesOnTheSurfaceAndNeverPassesThroughIt,
      // with AVX-512 BLAS kernels). Only a face turned by more than 60 degrees counts as
      // another face (a curved organ surface's neighbouring triangles do not), and only one
      // entered behind the tip: a steeper face ahead (a crease) is the tip's next contact.
      if ((!found || (hit.normal.dot(n) < 0.5 && hit.t < 0.5)) && surface_->firstEntry(x, p + n * r, p - n * r, under)) {
        hit = under;
        found = true;
      }
      if (found) {
        c->tissue = hit.material;
        c->frame = frameFrom(hit.normal);
      } else {
        // No surface under the tip: it slid off an edge. The contact is lost, and detection
        // looks for the surface again.
        Track& tr = tracks_[c->needle];
        tr.state = tr.has_path ? InsertionState::Out : InsertionState::Approaching;
        lost = true;
        continue;
      }
    }
    const Vec3 pT = c->tissue.interpolate(mesh, x);
    const CentreLinePoint cl = centreLinePoint(*needles_[c->needle], c->s);
    if (c->kind() != ConstraintKind::Puncture) c->frame = frameFrom(cl.axis);
    c->gap = c->frame.transpose() * (cl.position - pT);
    if (c->kind() == ConstraintKind::Shaft) c->compliance = interfaceCompliance(c->needle, c->tissue.element);
    if (c->kind() == ConstraintKind::Tip) {
      auto& tip = static_cast<TipConstraint&>(*c);
      if (tip.bevel()) {
        // The bevel direction is perpendicular to the tip's own axis; the rows' frame is the
        // centre line's at the tip, the same axis up to the beam's interpolation.
        const Vec3 b = nd.bevelDirection();
        tip.setBevelDirection((b - cl.axis.dot(b) * cl.axis).normalized());
      }
    }
    kept.push_back(std::move(c));
  }
  constraints_ = std::move(kept);
  return lost;
}

void NeedleTissueInteraction::detect(int n, double h) {
  Track& tr = tracks_[n];
  if (tr.state != InsertionState::Approaching && tr.state != InsertionState::Out) return;
  if (tr.sheathed) return;  // inside another needle: it meets no tissue
  const VecX& xT = tissue_->positions();
  const NeedleBody& nd = *needles_[n];
  const int tip = nd.beam().numNodes() - 1;
  const Vec3 p = nd.state().p[tip];
  const Vec3 v = nd.velocities().segment<3>(6 * tip) + nd.velocityChange().segment<3>(6 * tip);
  const Vec3 axis = (p - nd.state().p[tip - 1]).normalized();
  const double reach = h * v.norm() + 1e-9;
  SurfaceHit hit;
  // Along the axis around the tip when it moves forward, and along the tip's own path over
  // the step: a bent or buckled needle whose tip sweeps sideways into the surface, even
  // backwards along its axis as it straightens, meets it too (a path that leaves the tissue
  // enters nothing).
  const bool axial = v.dot(axis) > 0 && surface_->firstEntry(xT, p - axis * reach, p + axis * (reach + h * v.dot(axis)), hit);
  if (!axial && !(v.squaredNorm() > 0 && surface_->firstEntry(xT, p - v * h, p + v * (2 * h), hit))) return;
  auto c = std::make_unique<PunctureConstraint>(settings_.friction);
  c->tissue = hit.material;
  c->needle = n;
  c->frame = frameFrom(hit.normal);
  constraints_.push_back(std::move(c));
  tr.state = InsertionState::InContact;
}

InteractionStats NeedleTissueInteraction::solve(double h) {
  const auto t0 = steadyNow();
  InteractionStats st;

  // 1. Contact detection for needles not in the tissue; a tip that slid off the surface it
  //    touched (its point lost in updateGeometry) is looked for again at once, so that it
  //    meets the next face in this very step.
  for (size_t n = 0; n < needles_.size(); ++n) detect(static_cast<int>(n), h);
  if (updateGeometry()) {
    const size_t before = constraints_.size();
    for (size_t n = 0; n < needles_.size(); ++n) detect(static_cast<int>(n), h);
    if (constraints_.size() > before) updateGeometry();
  }
  // The touch's impact, armed while a puncture point carries no force (afterCommit): the
  // impulse m v that brings the surface point to the tip's approach speed, 1/m = sum_a w_a^2/m_a
  // (the point's share of the tissue's lumped mass).
  for (auto& c : constraints_) {
    auto* pc = c->kind() == ConstraintKind::Puncture ? static_cast<PunctureConstraint*>(c.get()) : nullptr;
    if (!pc || pc->wasLoaded()) continue;
    const NeedleBody& nd = *needles_[c->needle];
    const Vec3 v_tip = nd.velocities().segment<3>(6 * (nd.beam().numNodes() - 1));
    const Vec3 v_surface = c->tissue.interpolate(tissue_->mesh(), tissue_->velocities());
    double inv_mass = 0;
    for (int a = 0; a < 8; ++a) {
      const double m = tissue_->lumpedMass()[3 * tissue_->mesh().element(c->tissue.element)[a]], w = c->tissue.weights[a];
      inv_mass += w == 0 ? 0.0 : m > 0 ? w * w / m : std::numeric_limits<double>::infinity();
    }
    const double approach = std::max(0.0, -c->frame.col(0).dot(v_tip - v_surface));
    pc->armImpact(inv_mass > 0 && std::isfinite(inv_mass) ? approach / inv_mass : 0.0);
  }
  st.points = static_cast<int>(constraints_.size());
  if (constraints_.empty()) {
    st.ms = msSince(t0);
    return st;
  }

  // 2-3. Rows over the DOFs they touch; compliance from each body's factor; the rows'
  //      free velocities.
  const int np = st.points, m = 3 * np;
  ConstraintRows rows;
  rows.build(constraints_, *tissue_, needles_, column_of_);
  Eigen::MatrixXd W = rows.delassus(*tissue_, needles_, h);
  const VecX u_free = rows.freeVelocity(*tissue_, needles_);

  // A tiny compliance on every row (1e-8 of the largest diagonal entry) keeps W positive
  // definite when shaft points closer together than the nodes make rows redundant.
  {
    const double eps = 1e-8 * W.diagonal().maxCoeff();
    W.diagonal().array() += eps;
  }
  // Compliant ties (interface_compliance.hpp): the row asks gap + h u = -compliance * lambda,
  // i.e. (W + compliance / h) lambda = -gap / h - u_free.
  for (int p = 0; p < np; ++p)
    if (constraints_[p]->compliance > 0)
      for (int k = 1; k < 3; ++k) W(3 * p + k, 3 * p + k) += constraints_[p]->compliance / h;
  // 4. The constraint solve (block active set, or the paper's projected Gauss-Seidel),
  //    warm-started from the last multipliers.
  std::vector<ContactConstraint*> cs;
  VecX lambda(m);
  for (int p = 0; p < np; ++p) {
    cs.push_back(constraints_[p].get());
    lambda.segment<3>(3 * p) = constraints_[p]->lambda;
  }
  // Force scale for the convergence test: the interaction's strengths (or 1 mN).
  const double force_scale = std::max({settings_.puncture_force, settings_.cutting_force, 1e-3});
  const auto solve = settings_.solver == ConstraintSolver::GaussSeidel ? projectedGaussSeidel : blockActiveSet;
  const ConstraintSolveResult r =
      solve(W, u_free, cs, h, settings_.tolerance, settings_.max_iterations, force_scale, lambda);
  st.iterations = r.iterations;
  st.residual = r.residual;
  st.converged = r.converged;
  if (!lambda.allFinite()) throw NumericalError(-1, "constraint solve produced NaN/Inf");
  for (int p = 0; p < np; ++p) {
    constraints_[p]->lambda = lambda.segment<3>(3 * p);
    if (constraints_[p]->kind() == ConstraintKind::Puncture) static_cast<PunctureConstraint&>(*constraints_[p]).spendImpact(h);
  }

  // 5. Corrections dv = h A^-1 H^T lambda for each body.
  rows.correct(lambda, h, *tissue_, needles_);
  st.ms = msSince(t0);
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
      // The first loaded steps bring the surface to the tip's speed (rigid contact: an
      // inelastic impact, its force about m v / h, growing as the step shrinks): that part
      // (solve()) is not the tissue's resistance and does not puncture. On soft tissue at 1 ms
      // steps it exceeded the puncture force at the touch (doc/method.md, "The touch's impact
      // does not puncture").
      auto& pc = static_cast<PunctureConstraint&>(c);
      const double resisting = c.lambda[0] - pc.impact();
      pc.setWasLoaded(c.lambda[0] > 0);
      if (resisting > settings_.puncture_force) {
        // Puncture: the tip is tied to the tissue where it touched; the path starts there.
        tr.puncture_force = c.lambda[0];
        auto t = makeTip(c.needle);
        t->tissue = c.tissue;
        tr.next_shaft_rest = c.tissue.rest;
        tr.cut_length = 0;
        tr.next_shaft_at = 0;
        tr.path.clear();
        extendPath(c.needle, c.tissue.rest);
        if (t->bevel()) {
          // The entry hole holds a bevel tip's needle from the start: the tip's lateral tie
          // gives way to the bevel's load as soon as it cuts, and the needle outside the
          // tissue is long and slender (doc/method.md "Bevel tip").
          auto e = std::make_unique<ShaftConstraint>(settings_.friction, grip(c.needle));
          e->tissue = c.tissue;
          e->needle = c.needle;
          created.push_back(std::move(e));
          tr.next_shaft_at = settings_.shaft_spacing;
        }
        tr.has_path = true;
        tr.state = InsertionState::Punctured;
        created.push_back(std::move(t));
        it = constraints_.erase(it);
        continue;
      }
      // Lifted off: no force, and the tip farther from the surface than its own radius. Nearer,
      // the point stays (the unilateral law lets it separate): a surface springing back after
      // an indentation, or a buckled tip sliding on it, is still met instead of being passed.
      if (c.lambda[0] <= 0 && gap > nd.beam().section().outer_radius) {
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
          tr.cut_length += (anchor.rest - c.tissue.rest).norm();
          layShaftPoints(c.needle, anchor, created);
          c.tissue = anchor;
          extendPath(c.needle, anchor.rest);
          tipc.setWasCutting(true);
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
        tr.path_end = c.tissue;
        tr.has_end = true;
        tr.release_base = nd.state().p[0];
        it = constraints_.erase(it);
        continue;
      } else {
        tipc.setWasCutting(false);
        if (tr.state == InsertionState::Punctured) tr.state = InsertionState::Inserted;
      }
    }
    ++it;
  }
  // A withdrawing needle pushed past the end of its cut path cuts on from there.
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    if (tr.state != InsertionState::Withdrawing || !tr.has_end) continue;
    const NeedleBody& nd = *needles_[n];
    const Vec3 tip = nd.tipPosition();
    const Vec3 axis = (tip - nd.state().p[nd.beam().numNodes() - 2]).normalized();
    if (axis.dot(tip - tr.path_end.interpolate(mesh, x)) <= 0) continue;
    auto t = makeTip(static_cast<int>(n));
    t->tissue = tr.path_end;
    created.push_back(std::move(t));
    tr.state = InsertionState::Inserted;
    tr.has_end = false;
  }
  // A needle whose tip comes out of its sheath inside the tissue is tied there.
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    const bool sheathed = sheathOf(needles_, static_cast<int>(n), 1e-3 * settings_.shaft_spacing) >= 0;
    if (tr.sheathed && !sheathed && (tr.state == InsertionState::Approaching || tr.state == InsertionState::Out ||
                                     tr.state == InsertionState::Inserted)) {
      bool has_tip = false;
      for (const auto& c : constraints_) has_tip |= c->needle == static_cast<int>(n) && c->kind() == ConstraintKind::Tip;
      EmbeddedPoint anchor;
      if (!has_tip && locateCurrent(needles_[n]->tipPosition(), -1, anchor)) {
        auto t = makeTip(static_cast<int>(n));
        t->tissue = anchor;
        tr.path.clear();
        extendPath(static_cast<int>(n), anchor.rest);
        created.push_back(std::move(t));
        tr.state = InsertionState::Inserted;
        tr.has_path = true;
        tr.next_shaft_rest = anchor.rest;
        tr.cut_length = 0;
        tr.next_shaft_at = 0;
      }
    }
    tr.sheathed = sheathed;
  }
  for (auto& c : created) constraints_.push_back(std::move(c));
  for (size_t n = 0; n < needles_.size(); ++n) {
    Track& tr = tracks_[n];
    if (tr.has_path && activePoints(static_cast<int>(n)) == 0 &&
        (tr.state == InsertionState::Withdrawing || tr.state == InsertionState::Inserted)) {
      tr.state = InsertionState::Out;
      tr.has_end = false;  // out of the tissue: a new insertion punctures again
    }
  }
}

}  // namespace needle_sim
