#pragma once
// Duty-cycled spinning (Minhas, Engh, Fenske and Riviere 2007; doc/method.md "Needle", duty-cycled spinning):
// a bevel-tipped needle inserted while it spins cuts a nearly straight path; inserted
// without spinning, an arc of the bevel's curvature kappa_max. Alternating the two, in whole
// turns so that the bevel comes back to the commanded roll at the end of each cycle, gives
// an effective curvature of about kappa_max (1 - duty), duty the fraction of the time spent
// spinning.
//
// A motion segment with spin_duty > 0 becomes ordinary keyframes: N cycles of the
// segment's duration T (N turns in all, N = max(1, round(duty T rate / 2 pi))), each cycle
// first turning by 2 pi over duty T / N, then holding the roll for (1 - duty) T / N, the
// position and axis interpolated as the segment's own; later keys' rolls are advanced by the
// 2 pi N turned, so the base never unwinds.
#include <stdexcept>
#include <vector>

#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/needle/needle_parameters.hpp"

namespace needle_sim {

// Throws std::invalid_argument for a duty outside [0, 1], a negative or non-finite rate, or
// a duty > 0 with a zero rate.
std::vector<NeedleMotionKey> expandDutyCycledSpin(const std::vector<NeedleMotionKey>& keys, const BasePose& rest);

}  // namespace needle_sim
