#pragma once
// Displacement control for the static Newton solve (TissueBody::solveStatic, doc/method.md
// "Brain shift"): a load s * unit whose scale s is unknown besides x, fixed by one scalar
// constraint c(x) = 0 (e.g. "the target has moved by 6.5 mm"). Each Newton step solves the
// bordered system  K dx - ds unit = r,  grad c . dx = -c  with two solves by one matrix,
// dx = K^-1 r + ds K^-1 unit, so the scale and the equilibrium converge together instead of
// an equilibrium per trial scale.
#include <functional>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct LoadControl {
  const VecX* unit = nullptr;                                    // load per unit scale (3n)
  std::function<double(const VecX& x, VecX& grad)> constraint;  // c(x) [m] and dc/dx (3n)
  double tolerance = 0;                                          // |c| to reach [m]
  double scale = 0;           // in: the scale of `unit` inside the external load; out: reached
  double max_scale = 1e3;     // beyond it the constraint is out of reach (NumericalError)
  double max_growth = 4;      // one step changes the scale by at most this factor (either way)
};

}  // namespace needle_sim
