#pragma once
// A needle-tissue constraint point (paper §2.1): a tissue material point (embedded in a
// hexahedron) joined to a point of a needle (by arc length) through three rows, the
// columns of `frame`. Row k measures the relative velocity u_k = d_k . (v_needle - v_tissue);
// its multiplier lambda_k is the force on the needle along d_k (the tissue gets the opposite).
//
// Each law is a small subclass: the velocity each row aims at over the step (target) and
// the projection of the multipliers onto its admissible set (project), which the projected
// Gauss-Seidel solver applies after updating a row.
#include <limits>
#include <memory>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/embedded_point.hpp"

namespace needle_sim {

enum class ConstraintKind { Puncture, Tip, Shaft };

class ContactConstraint {
 public:
  virtual ~ContactConstraint() = default;
  virtual ConstraintKind kind() const = 0;
  // A copy of the same law and state (a simulation copied for a prediction).
  virtual std::unique_ptr<ContactConstraint> clone() const = 0;
  // Relative velocity wanted at the end of the step, per row (default: close the gap).
  virtual Vec3 target(double h) const { return -gap / h; }
  // Projects lambda onto the law's admissible set after row `row` was updated.
  virtual void project(Vec3& lambda, int row) const = 0;
  // Tip and shaft: the interval row 0 (axial) must lie in, given the lateral forces
  // lambda[1..2] (friction, cutting); the block solver freezes it per outer iteration.
  virtual void axialBounds(const Vec3& lambda, double& lo, double& hi) const {
    (void)lambda;
    lo = -std::numeric_limits<double>::infinity();
    hi = std::numeric_limits<double>::infinity();
  }
  // A row whose force the law sets outright (a bevel tip's lateral load while it cuts):
  // true, with the force in `value`. Such rows are moved to the right-hand side before the
  // solve (ReducedContactProblem).
  virtual bool prescribed(int row, double& value) const {
    (void)row;
    (void)value;
    return false;
  }

  EmbeddedPoint tissue;     // tissue material point
  int needle = 0;           // index of the needle
  double s = 0;             // arc length of the needle point from the base (rest length)
  Mat3 frame = Mat3::Identity();  // row directions (world), columns
  Vec3 gap = Vec3::Zero();        // d_k . (p_needle - p_tissue) at the start of the step
  Vec3 lambda = Vec3::Zero();     // forces of the last solve [N] (also the warm start)
  // Compliance of the lateral rows (1, 2) [m/N]: the tie stretches by compliance * lambda
  // (interaction.lateral_stiffness); 0 for a rigid tie.
  double compliance = 0;
};

}  // namespace needle_sim
