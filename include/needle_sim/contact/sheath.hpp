#pragma once
// Needles inside needles (DBS: the electrode rides in the cannula's lumen), doc/method.md
// "Several needles": a needle whose tip lies inside another's lumen touches no tissue; a
// shaft point that a withdrawing needle leaves passes to another needle running through it.
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/needle/needle_body.hpp"

namespace needle_sim {

// Index of a needle whose lumen holds needle n's tip (its inner radius at least n's outer
// radius, the tip within its length plus `slack` and within its inner radius of its axis),
// or -1.
int sheathOf(const std::vector<NeedleBody*>& needles, int n, double slack);
// Another needle than `from` whose centre line passes within the sum of the two radii of
// p, strictly inside its length: its index (s set to the arc length there), or -1.
int needleThrough(const std::vector<NeedleBody*>& needles, int from, const Vec3& p, double& s);

}  // namespace needle_sim
