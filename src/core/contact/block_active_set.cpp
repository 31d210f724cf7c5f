#include <Eigen/Cholesky>
#include <cmath>

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

// One puncture block: u = A l + b with unilateral normal (row 0) and the Coulomb cone on
// the tangents, by alternating the exact normal and tangential solves in 3x3.
void punctureBlock(const Mat3& A, const Vec3& b, double mu, Vec3& l) {
  for (int k = 0; k < 200; ++k) {
    const Vec3 prev = l;
    l[0] = A(0, 0) > 0 ? std::max(0.0, -(b[0] + A(0, 1) * l[1] + A(0, 2) * l[2]) / A(0, 0)) : 0.0;
    const Eigen::Vector2d c = b.tail<2>() + A.block<2, 1>(1, 0) * l[0];
    l.tail<2>() = discQp(A.block<2, 2>(1, 1), c, mu * l[0]);
    if ((l - prev).lpNorm<Eigen::Infinity>() <= 1e-14 * std::max(l.lpNorm<Eigen::Infinity>(), 1e-300)) break;
  }
}

}  // namespace

// Outer fixed point: freeze the axial rows' bounds at the current lateral forces, solve the
// axial box QP exactly (puncture forces fixed), then each puncture block exactly (the rest
// fixed), recompute the lateral forces; stop when an iteration changes no multiplier by
// more than tolerance (relative, see ConstraintSolveResult). With friction below about 1 the
// bounds' dependence on the lateral forces is a contraction, and without puncture blocks
// and lateral-dependent bounds a single iteration is exact.
ConstraintSolveResult blockActiveSet(const Eigen::MatrixXd& W, const VecX& u_free,
                                     const std::vector<ContactConstraint*>& c, double h, double tol, int max_it,
                                     double force_scale, VecX& lambda) {
  const ReducedContactProblem rp(W, u_free, c, h);
  std::vector<int> ax, punct;  // F indices of the axial rows; constraints with a puncture block
  for (size_t i = 0; i < rp.F.size(); ++i) {
    const int row = rp.F[i];
    if (c[row / 3]->kind() != ConstraintKind::Puncture) ax.push_back(static_cast<int>(i));
    else if (row % 3 == 0) punct.push_back(row / 3);
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
  for (int it = 1; it <= std::max(1, max_it); ++it) {
    const VecX old = lambda;
    if (na > 0) {
      const VecX uF = rp.qF + rp.S * lF;
      for (int a = 0; a < na; ++a) {
        const int i = ax[a], p = rp.F[i] / 3;
        c[p]->axialBounds(lambda.segment<3>(3 * p), lo[a], hi[a]);
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
      punctureBlock(A, b, static_cast<const PunctureConstraint*>(c[p])->friction(), l);
      lF.segment<3>(i0) = l;
    }
    rp.scatter(lF, lambda);
    if (recordIteration(r, it, (lambda - old).lpNorm<Eigen::Infinity>(), lambda, force_scale, tol)) break;
  }
  projectOntoLaws(c, lambda);
  return r;
}

}  // namespace needle_sim
