#pragma once
// The needle-tissue interface's lateral stiffness (doc/method.md "Interface compliance").
//
// A shaft point ties the needle's centre line to one tissue material point. The hexahedra
// around it are millimetres wide, the needle a fraction of that: the mesh does not resolve
// the strain concentrated near the needle wall, so a rigid tie makes the needle's lateral
// support as stiff as the mesh is coarse, and a load at the needle's tip then bends it over
// a free length set by the shaft points' spacing, not by the tissue. The missing near field
// is an elastic annulus between the needle wall (radius r) and the scale R the mesh resolves:
// in plane strain a line force q on a rigid disc moves it, relative to the ring at R, by
//   q (3 - 4 nu) ln(R / r) / (8 pi G (1 - nu))
// (the 2-D Kelvin solution's logarithmic term; its angular term is scale-free and cancels).
// Its inverse is a Winkler foundation modulus k [N/m per m of needle]; each shaft point
// carries its share of the path, so its tie's compliance is 1 / (k * spacing).
#include <algorithm>
#include <cmath>
#include <limits>

namespace needle_sim {

// The near field's lateral stiffness per unit length [Pa]; infinite (a rigid tie) once the
// mesh resolves the needle (R <= r).
inline double nearFieldLateralStiffness(double young, double poisson, double radius, double resolved) {
  const double shear = young / (2 * (1 + poisson));
  const double log_ratio = std::log(resolved / radius);
  if (!(log_ratio > 0)) return std::numeric_limits<double>::infinity();
  return 8 * M_PI * shear * (1 - poisson) / ((3 - 4 * poisson) * log_ratio);
}

// The radius out to which the mesh leaves the field unresolved around a needle of radius r
// in hexahedra of mean edge h: the needle wall plus half an edge (the distance from the line
// to the element's nodes, which carry its load). The tie is rigid only in the limit h -> 0.
inline double resolvedRadius(double element_edge, double radius) { return radius + 0.5 * element_edge; }

}  // namespace needle_sim
