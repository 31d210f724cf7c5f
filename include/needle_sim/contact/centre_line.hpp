#pragma once
// The needle's centre line as the constraints see it (doc/method.md, "Needle-tissue
// constraints"): between two beam nodes, the cubic Hermite curve of the element, from the
// end positions and the end tangents of the node orientations, so that constraint points
// between nodes see the needle's curvature; a point's velocity involves the nodes' spins
// through the same weights (d . v = h00 d.v_a + h10 l (t_a x d).w_a + h01 d.v_b + h11 l (t_b x d).w_b).
#include "needle_sim/core/types.hpp"
#include "needle_sim/needle/needle_body.hpp"

namespace needle_sim {

// Cubic Hermite basis at xi in [0, 1]: values (position) and derivatives (tangent).
struct HermiteWeights {
  double h00, h10, h01, h11;  // end a, tangent a, end b, tangent b
  double d00, d10, d01, d11;  // d/dxi
};
HermiteWeights hermite(double xi);

struct CentreLinePoint {
  int element = 0;  // beam element (nodes element, element + 1)
  double xi = 0;    // parameter along it, [0, 1]
  Vec3 position = Vec3::Zero();
  Vec3 axis = Vec3::UnitX();  // unit tangent
  double chord = 0;  // current distance between the element's nodes (scales the tangent terms)
};

// The point at rest arc length s from the base (clamped to the needle).
CentreLinePoint centreLinePoint(const NeedleBody& needle, double s);
// Rest arc length of the centre-line point closest to p (on the polyline of the nodes),
// clamped at the base but not beyond the tip: a point the needle has been withdrawn past
// gets s > L.
double closestArcLength(const NeedleBody& needle, const Vec3& p);
// Velocity of the centre-line point at (element 0, xi) due to the base node's velocity and
// spin alone (the prescribed base enters the constraint rows this way).
Vec3 baseDrivenVelocity(const NeedleBody& needle, double xi, const Vec3& v_base, const Vec3& w_base);
// Distance of p from the needle's axis line at its closest centre-line point.
double distanceFromAxis(const NeedleBody& needle, double s, const Vec3& p);

}  // namespace needle_sim
