#include <Eigen/Cholesky>
#include <cmath>
#include <limits>
#include <vector>

#include "needle_sim/contact/constraint_solve.hpp"
#include "needle_sim/contact/puncture_constraint.hpp"

namespace needle_sim {

namespace {

// min 1/2 x'Mx + g'x subject to lo <= x <= hi, M small, dense and positive definite: a
// primal active-set method (Nocedal & Wright, Algorithm 16.3), which decreases the
// objective at every iteration and so ends in finitely many. The working set starts from
// the warm start (the rows whose projected gradient step leaves the interval), so a step like
// the last one costs a single solve. The factor of the free rows is kept while they repeat.
class BoxQp {
 public:
  explicit BoxQp(const Eigen::MatrixXd& M) : M_(M) {}

  // eps: absolute tolerance of the KKT conditions (a multiplier smaller than eps does not
  // release its row). Returns the iterations, or -1 if the cap was hit.
  int solve(const VecX& g, const VecX& lo, const VecX& hi, double eps, VecX& x) {
    const int n = static_cast<int>(g.size());
    if (n == 0) return 0;
    enum State : char { Lo, Hi, Free };
    std::vector<char> s(n);
    {
      const VecX grad = M_ * x + g;
      for (int i = 0; i < n; ++i) {
        const double v = x[i] - grad[i] / M_(i, i);
        s[i] = lo[i] >= hi[i] || v <= lo[i] ? Lo : v >= hi[i] ? Hi : Free;
        x[i] = s[i] == Lo ? lo[i] : s[i] == Hi ? hi[i] : std::clamp(x[i], lo[i], hi[i]);
      }
    }
    const int max_it = 10 * n + 50;
    for (int it = 1; it <= max_it; ++it) {
      std::vector<int> fr;
      for (int i = 0; i < n; ++i)
        if (s[i] == Free) fr.push_back(i);
      // Step to the minimum with the working set fixed.
      VecX p = VecX::Zero(n);
      if (!fr.empty()) {
        if (fr != free_) factor(fr);
        VecX rhs(fr.size());
        const VecX grad = M_ * x + g;
        for (size_t a = 0; a < fr.size(); ++a) rhs[static_cast<Eigen::Index>(a)] = -grad[fr[a]];
        const VecX pf = ldlt_.solve(rhs);
        for (size_t a = 0; a < fr.size(); ++a) p[fr[a]] = pf[static_cast<Eigen::Index>(a)];
      }
      if (p.lpNorm<Eigen::Infinity>() <= eps) {
        // At the working set's minimum: release the bound row with the largest wrong-signed
        // multiplier (the gradient pulling it inside its interval), or stop.
        x += p;
        const VecX grad = M_ * x + g;
        int worst = -1;
        double wv = eps;
        for (int i = 0; i < n; ++i) {
          if (s[i] == Free || lo[i] >= hi[i]) continue;
          const double pull = std::min((s[i] == Lo ? -grad[i] : grad[i]) / M_(i, i), hi[i] - lo[i]);
          if (pull > wv) wv = pull, worst = i;
        }
        if (worst < 0) return it;
        s[worst] = Free;
        continue;
      }
      // Move as far as the first blocking bound.
      double alpha = 1;
      int block = -1;
      for (int i : fr) {
        const double room = p[i] < 0 ? (lo[i] - x[i]) / p[i] : p[i] > 0 ? (hi[i] - x[i]) / p[i] : 1;
        if (room < alpha) alpha = std::max(room, 0.0), block = i;
      }
      x += alpha * p;
      if (block >= 0) {
        s[block] = p[block] < 0 ? Lo : Hi;
        x[block] = p[block] < 0 ? lo[block] : hi[block];
      }
    }
    return -1;
  }

 private:
  void factor(const std::vector<int>& fr) {
    Eigen::MatrixXd Mi(fr.size(), fr.size());
    for (size_t a = 0; a < fr.size(); ++a)
      for (size_t b = 0; b < fr.size(); ++b) Mi(static_cast<Eigen::Index>(a), static_cast<Eigen::Index>(b)) = M_(fr[a], fr[b]);
    ldlt_.compute(Mi);
    free_ = fr;
  }

  const Eigen::MatrixXd& M_;
  std::vector<int> free_;
  Eigen::LDLT<Eigen::MatrixXd> ldlt_;
};

// min 1/2 x'Bx + c'x over the disc |x| <= r (B 2x2 positive definite): inside, the free
// minimum; else x = -(B + nu I)^-1 c with |x| = r, nu >= 0 by bisection (|x(nu)| falls with
// nu). Its KKT condition, B x + c = -nu x, is Coulomb's maximal dissipation: the friction
// force opposes the slip velocity B x + c.
Eigen::Vector2d discQp(const Eigen::Matrix2d& B, const Eigen::Vector2d& c, double r) {
  if (!(r > 0)) return Eigen::Vector2d::Zero();
  Eigen::Vector2d x = -B.ldlt().solve(c);
  if (x.norm() <= r) return x;
  double a = 0, b = c.norm() / r;  // |x(b)| <= |c| / b = r
  for (int k = 0; k < 80 && b - a > 1e-15 * b; ++k) {
    const double nu = 0.5 * (a + b);
    x = -(B + nu * Eigen::Matrix2d::Identity()).ldlt().solve(c);
    (x.norm() > r ? a : b) = nu;
  }
  x = -(B + b * Eigen::Matrix2d::Identity()).ldlt().solve(c);
  const double nx = x.norm();
  return nx > 0 ? Eigen::Vector2d(x * (r / nx)) : x;
}

// A puncture block's tangential rows: u_t = A_tt l_t + c with the Coulomb disc |l_t| <= mu l_n,
// the normal force l_n fixed by the box QP.
void punctureTangents(const Mat3& A, const Vec3& b, double mu, Vec3& l) {
  const Eigen::Vector2d c = b.tail<2>() + A.block<2, 1>(1, 0) * l[0];
  l.tail<2>() = discQp(A.block<2, 2>(1, 1), c, mu * l[0]);
}

// Anderson acceleration of a fixed point x = G(x) (Walker & Ni, SIAM J. Numer. Anal. 49(4),
// 2011, "type II", depth m): from the last differences of the iterates' images and residuals,
// the combination of images whose residual is least. Restarted when the residual grows (the
// outer map is piecewise smooth: an active set or a slip changed).
class Anderson {
 public:
  explicit Anderson(int depth) : m_(depth) {}

  // x: the iterate, gx = G(x). Returns the next iterate.
  VecX next(const VecX& x, const VecX& gx) {
    const VecX f = gx - x;
    if (has_last_ && f.norm() > f_last_.norm()) dF_.clear(), dG_.clear();
    else if (has_last_) {
      dF_.push_back(f - f_last_);
      dG_.push_back(gx - g_last_);
      if (static_cast<int>(dF_.size()) > m_) dF_.erase(dF_.begin()), dG_.erase(dG_.begin());
    }
    f_last_ = f, g_last_ = gx, has_last_ = true;
    if (dF_.empty()) return gx;
    Eigen::MatrixXd F(f.size(), static_cast<Eigen::Index>(dF_.size()));
    for (size_t j = 0; j < dF_.size(); ++j) F.col(static_cast<Eigen::Index>(j)) = dF_[j];
    const VecX gamma = F.colPivHouseholderQr().solve(f);
    VecX out = gx;
    for (size_t j = 0; j < dG_.size(); ++j) out -= gamma[static_cast<Eigen::Index>(j)] * dG_[j];
    return out;
  }

 private:
  int m_;
  std::vector<VecX> dF_, dG_;
  VecX f_last_, g_last_;
  bool has_last_ = false;
};

}  // namespace

// Outer fixed point: freeze the axial rows' bounds at the current lateral forces and the
// puncture blocks' tangential forces, solve the box QP of the axial rows and the puncture
// normals (unilateral: [0, inf)) exactly, then each puncture block's tangential disc exactly
// (the rest fixed), recompute the bounds; stop when an iteration changes no multiplier by
// more than tolerance (relative, see ConstraintSolveResult). The rows along the needle (the
// axial rows and a puncture's normal, which a second needle pressing on the surface or the
// electrode in its cannula couple strongly) are in one exact solve, so the outer iteration
// only carries the lateral couplings. Without puncture blocks and lateral-dependent bounds
// a single iteration is exact. With slipping shaft points in soft tissue the bounds'
// dependence on the lateral forces is a contraction at a rate near 1 (0.98 measured on the
// 8x4x4 phantom at E = 6 kPa): Anderson acceleration makes it a few iterations.
ConstraintSolveResult blockActiveSet(const Eigen::MatrixXd& W, const VecX& u_free,
                                     const std::vector<ContactConstraint*>& c, double h, double tol, int max_it,
                                     double force_scale, VecX& lambda) {
  const ReducedContactProblem rp(W, u_free, c, h);
  std::vector<int> ax, punct;  // F indices of the axial rows; constraints with a puncture block
  for (size_t i = 0; i < rp.F.size(); ++i) {
    const int row = rp.F[i];
    if (c[row / 3]->kind() != ConstraintKind::Puncture) {
      ax.push_back(static_cast<int>(i));
    } else if (row % 3 == 0) {
      ax.push_back(static_cast<int>(i));  // the normal row, unilateral
      punct.push_back(row / 3);
    }
  }
  const int na = static_cast<int>(ax.size());
  Eigen::MatrixXd Saa(na, na);
  for (int a = 0; a < na; ++a)
    for (int b = 0; b < na; ++b) Saa(a, b) = rp.S(ax[a], ax[b]);
  BoxQp qp(Saa);
  VecX lF = rp.gatherF(lambda);
  rp.scatter(lF, lambda);
  VecX lo(na), hi(na), g(na), x(na);
  ConstraintSolveResult r;
  Anderson accelerate(5);
  for (int it = 1; it <= std::max(1, max_it); ++it) {
    const VecX old = lambda, x_it = lF;
    if (na > 0) {
      const VecX uF = rp.qF + rp.S * lF;
      for (int a = 0; a < na; ++a) {
        const int i = ax[a], p = rp.F[i] / 3;
        if (c[p]->kind() == ConstraintKind::Puncture) lo[a] = 0, hi[a] = std::numeric_limits<double>::infinity();
        else c[p]->axialBounds(lambda.segment<3>(3 * p), lo[a], hi[a]);
        x[a] = lF[i];
        g[a] = uF[i] - rp.target[rp.F[i]];
      }
      g.noalias() -= Saa * x;
      qp.solve(g, lo, hi, 1e-2 * tol * force_scale, x);
      for (int a = 0; a < na; ++a) lF[ax[a]] = x[a];
    }
    for (int p : punct) {
      const int i0 = rp.fpos[3 * p];  // the block's three rows are consecutive in F
      const Mat3 A = rp.S.block<3, 3>(i0, i0);
      Vec3 l = lF.segment<3>(i0);
      const Vec3 b = (rp.qF + rp.S * lF).segment<3>(i0) - A * l - rp.target.segment<3>(3 * p);
      punctureTangents(A, b, static_cast<const PunctureConstraint*>(c[p])->friction(), l);
      lF.segment<3>(i0) = l;
    }
    rp.scatter(lF, lambda);
    if (recordIteration(r, it, (lambda - old).lpNorm<Eigen::Infinity>(), lambda, force_scale, tol)) break;
    if (it < max_it) {
      lF = accelerate.next(x_it, lF);
      rp.scatter(lF, lambda);
    }
  }
  projectOntoLaws(c, lambda);
  return r;
}

}  // namespace needle_sim
