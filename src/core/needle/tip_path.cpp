#include "needle_sim/needle/tip_path.hpp"

#include <Eigen/SVD>
#include <cmath>

namespace needle_sim {

double pathLength(const std::vector<Vec3>& path) {
  double L = 0;
  for (size_t i = 1; i < path.size(); ++i) L += (path[i] - path[i - 1]).norm();
  return L;
}

Vec3 pointAtArcLength(const std::vector<Vec3>& path, double s) {
  if (path.empty()) return Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
  if (s <= 0) return path.front();
  for (size_t i = 1; i < path.size(); ++i) {
    const double l = (path[i] - path[i - 1]).norm();
    if (s <= l && l > 0) return path[i - 1] + (s / l) * (path[i] - path[i - 1]);
    s -= l;
  }
  return path.back();
}

double endCurvature(const std::vector<Vec3>& path, double window) {
  const double L = pathLength(path);
  if (!(window > 0) || L < window) return std::numeric_limits<double>::quiet_NaN();
  const Vec3 a = pointAtArcLength(path, L - window), b = pointAtArcLength(path, L - 0.5 * window), c = path.back();
  // Menger curvature: 4 area / product of the sides.
  const double ab = (b - a).norm(), bc = (c - b).norm(), ca = (a - c).norm();
  const double d = ab * bc * ca;
  return d > 0 ? 2 * (b - a).cross(c - a).norm() / d : 0.0;
}

std::vector<Vec3> pathStretch(const std::vector<Vec3>& path, double s0, double s1) {
  std::vector<Vec3> out;
  if (path.empty() || !(s1 > s0)) return out;
  out.push_back(pointAtArcLength(path, s0));
  double s = 0;
  for (size_t i = 0; i < path.size(); ++i) {
    if (i > 0) s += (path[i] - path[i - 1]).norm();
    if (s > s0 && s < s1) out.push_back(path[i]);
  }
  out.push_back(pointAtArcLength(path, s1));
  return out;
}

CircleFit fitCircle(const std::vector<Vec3>& pts) {
  CircleFit f;
  const int n = static_cast<int>(pts.size());
  if (n < 3) return f;
  Vec3 mean = Vec3::Zero();
  for (const Vec3& p : pts) mean += p;
  mean /= n;
  Eigen::MatrixXd X(n, 3);
  for (int i = 0; i < n; ++i) X.row(i) = (pts[i] - mean).transpose();
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(X, Eigen::ComputeThinV);
  const Vec3 e1 = svd.matrixV().col(0), e2 = svd.matrixV().col(1);
  f.normal = svd.matrixV().col(2);
  // Kasa: x^2 + y^2 = 2 a x + 2 b y + c in the plane, linear least squares.
  Eigen::MatrixXd A(n, 3);
  VecX rhs(n);
  double oop = 0;
  for (int i = 0; i < n; ++i) {
    const Vec3 d = pts[i] - mean;
    const double x = d.dot(e1), y = d.dot(e2);
    A.row(i) << 2 * x, 2 * y, 1;
    rhs[i] = x * x + y * y;
    oop += std::pow(d.dot(f.normal), 2);
  }
  f.rms_out_of_plane = std::sqrt(oop / n);
  const Vec3 sol = A.colPivHouseholderQr().solve(rhs);
  const double r2 = sol[2] + sol[0] * sol[0] + sol[1] * sol[1];
  if (!(r2 > 0) || !std::isfinite(r2)) return f;
  f.radius = std::sqrt(r2);
  f.curvature = 1 / f.radius;
  f.centre = mean + sol[0] * e1 + sol[1] * e2;
  double res = 0;
  for (int i = 0; i < n; ++i) {
    const Vec3 d = pts[i] - mean;
    const double x = d.dot(e1) - sol[0], y = d.dot(e2) - sol[1];
    res += std::pow(std::hypot(x, y) - f.radius, 2);
  }
  f.rms_residual = std::sqrt(res / n);
  f.ok = true;
  return f;
}

}  // namespace needle_sim
