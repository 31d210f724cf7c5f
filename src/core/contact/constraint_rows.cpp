#include "needle_sim/contact/constraint_rows.hpp"

#include <cmath>

#include "needle_sim/contact/centre_line.hpp"

namespace needle_sim {

void ConstraintRows::build(const std::vector<std::unique_ptr<ContactConstraint>>& constraints,
                           const TissueBody& tissue, const std::vector<NeedleBody*>& needles,
                           std::vector<int>& column_of) {
  const HexMesh& mesh = tissue.mesh();
  const DofMap& tdofs = tissue.dofs();
  const int np = static_cast<int>(constraints.size()), m = 3 * np;
  points_.clear();
  tcols_.clear();
  ncols_.assign(needles.size(), {});
  std::vector<std::vector<int>> ncol_of(needles.size());
  for (size_t n = 0; n < needles.size(); ++n) ncol_of[n].assign(needles[n]->dofs().numFree(), -1);
  for (int p = 0; p < np; ++p) {
    const auto& c = *constraints[p];
    for (int a = 0; a < 8; ++a)
      for (int d = 0; d < 3; ++d) {
        if (std::abs(c.tissue.weights[a]) < 1e-12) continue;  // e.g. a point on an element edge
        const int full = 3 * mesh.element(c.tissue.element)[a] + d;
        for (const DofWeight* x = tdofs.expansionBegin(full); x != tdofs.expansionEnd(full); ++x)
          if (column_of[x->free] < 0) {
            column_of[x->free] = static_cast<int>(tcols_.size());
            tcols_.push_back(x->free);
          }
      }
    const CentreLinePoint cl = centreLinePoint(*needles[c.needle], c.s);
    points_.push_back({c.needle, cl.element, cl.xi, c.frame});
    const DofMap& nd = needles[c.needle]->dofs();
    for (int node : {cl.element, cl.element + 1})
      for (int d = 0; d < 6; ++d) {
        const int f = nd.freeIndex(6 * node + d);
        if (f >= 0 && ncol_of[c.needle][f] < 0) {
          ncol_of[c.needle][f] = static_cast<int>(ncols_[c.needle].size());
          ncols_[c.needle].push_back(f);
        }
      }
  }
  HT_ = Eigen::MatrixXd::Zero(m, static_cast<Eigen::Index>(tcols_.size()));
  HN_.resize(needles.size());
  for (size_t n = 0; n < needles.size(); ++n) HN_[n] = Eigen::MatrixXd::Zero(m, static_cast<Eigen::Index>(ncols_[n].size()));
  for (int p = 0; p < np; ++p) {
    const auto& c = *constraints[p];
    const Point& pt = points_[p];
    const NeedleBody& body = *needles[pt.needle];
    const DofMap& nd = body.dofs();
    const HermiteWeights h = hermite(pt.xi);
    const double l = (body.state().p[pt.element + 1] - body.state().p[pt.element]).norm();
    const double wt[2] = {h.h00, h.h01};
    const double wr[2] = {h.h10 * l, h.h11 * l};
    for (int k = 0; k < 3; ++k) {
      const Vec3 d = pt.frame.col(k);
      for (int a = 0; a < 8; ++a)
        for (int j = 0; j < 3; ++j) {
          if (std::abs(c.tissue.weights[a]) < 1e-12) continue;
          const int full = 3 * mesh.element(c.tissue.element)[a] + j;
          for (const DofWeight* x = tdofs.expansionBegin(full); x != tdofs.expansionEnd(full); ++x)
            HT_(3 * p + k, column_of[x->free]) -= c.tissue.weights[a] * x->weight * d[j];
        }
      for (int q = 0; q < 2; ++q) {
        const Vec3 rot = (body.state().q[pt.element + q] * body.beam().restDirection()).cross(d) * wr[q];
        for (int j = 0; j < 3; ++j) {
          const int ft = nd.freeIndex(6 * (pt.element + q) + j), fr = nd.freeIndex(6 * (pt.element + q) + 3 + j);
          if (ft >= 0) HN_[pt.needle](3 * p + k, ncol_of[pt.needle][ft]) += wt[q] * d[j];
          if (fr >= 0) HN_[pt.needle](3 * p + k, ncol_of[pt.needle][fr]) += rot[j];
        }
      }
    }
  }
  for (int f : tcols_) column_of[f] = -1;
}

Eigen::MatrixXd ConstraintRows::delassus(const TissueBody& tissue, const std::vector<NeedleBody*>& needles,
                                         double h) const {
  const Eigen::Index m = HT_.rows();
  Eigen::MatrixXd C, W = Eigen::MatrixXd::Zero(m, m);
  if (!tcols_.empty()) {
    tissue.complianceBlock(tcols_, C);
    W.noalias() += HT_ * (C * HT_.transpose());
  }
  for (size_t n = 0; n < needles.size(); ++n) {
    if (ncols_[n].empty()) continue;
    needles[n]->complianceBlock(ncols_[n], C);
    W.noalias() += HN_[n] * (C * HN_[n].transpose());
  }
  return h * W;
}

VecX ConstraintRows::freeVelocity(const TissueBody& tissue, const std::vector<NeedleBody*>& needles) const {
  VecX u = VecX::Zero(HT_.rows());
  const DofMap& tdofs = tissue.dofs();
  VecX vT(tcols_.size());
  const VecX& v = tissue.velocities();
  const VecX& dv = tissue.velocityChangeFree();
  for (size_t i = 0; i < tcols_.size(); ++i)
    vT[static_cast<Eigen::Index>(i)] = v[tdofs.freeToFull()[tcols_[i]]] + dv[tcols_[i]];
  u += HT_ * vT;
  for (size_t n = 0; n < needles.size(); ++n) {
    if (ncols_[n].empty()) continue;
    const DofMap& nd = needles[n]->dofs();
    VecX vN(ncols_[n].size());
    for (size_t i = 0; i < ncols_[n].size(); ++i) {
      const int full = nd.freeToFull()[ncols_[n][i]];
      vN[static_cast<Eigen::Index>(i)] = needles[n]->velocities()[full] + needles[n]->velocityChange()[full];
    }
    u += HN_[n] * vN;
  }
  // The rows' dependence on the prescribed needle base (moving with the command).
  for (size_t p = 0; p < points_.size(); ++p) {
    const Point& pt = points_[p];
    if (pt.element != 0) continue;
    const NeedleBody& nd = *needles[pt.needle];
    const Vec3 vb = nd.velocities().head<3>() + nd.velocityChange().head<3>();
    const Vec3 wb = nd.velocities().segment<3>(3) + nd.velocityChange().segment<3>(3);
    u.segment<3>(3 * p) += pt.frame.transpose() * baseDrivenVelocity(nd, pt.xi, vb, wb);
  }
  return u;
}

void ConstraintRows::correct(const VecX& lambda, double h, TissueBody& tissue,
                             const std::vector<NeedleBody*>& needles) const {
  if (!tcols_.empty()) tissue.addInverseColumns(tcols_, h * (HT_.transpose() * lambda));
  for (size_t n = 0; n < needles.size(); ++n)
    if (!ncols_[n].empty()) needles[n]->addInverseColumns(ncols_[n], h * (HN_[n].transpose() * lambda));
}

}  // namespace needle_sim
