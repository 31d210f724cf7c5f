#pragma once
// The path a needle tip cut (NeedleTissueInteraction::cutPath, a polyline in rest space) and
// its shape: its length, the curvature of its last stretch, and a least-squares circle
// through a stretch (the kinematic "unicycle" model of bevel steering, Webster et al. 2006,
// says a bevel tip inserted without turning cuts an arc of constant curvature).
#include <limits>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

double pathLength(const std::vector<Vec3>& path);

// The point at arc length s along the path (clamped to its ends).
Vec3 pointAtArcLength(const std::vector<Vec3>& path, double s);

// Curvature [1/m] of the circle through the points at arc lengths L - window, L - window/2
// and L (L the path's length): the path's bending over its last `window`. NaN when the
// path is shorter than the window.
double endCurvature(const std::vector<Vec3>& path, double window);

struct CircleFit {
  bool ok = false;
  Vec3 centre = Vec3::Zero();
  Vec3 normal = Vec3::Zero();  // of the best plane through the points
  double radius = std::numeric_limits<double>::infinity();
  double curvature = 0;           // 1 / radius
  double rms_residual = 0;        // of the distances to the circle, in its plane [m]
  double rms_out_of_plane = 0;    // of the distances to the plane [m]
};

// Least-squares plane (SVD), then the algebraic circle fit in that plane (Kasa); at least 3
// points not on one line. A straight path gives curvature ~0 (and ok false if exactly so).
CircleFit fitCircle(const std::vector<Vec3>& points);

// The part of a path between arc lengths s0 and s1 (its points in between, plus both ends).
std::vector<Vec3> pathStretch(const std::vector<Vec3>& path, double s0, double s1);

}  // namespace needle_sim
