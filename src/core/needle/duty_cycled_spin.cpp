#include "needle_sim/needle/duty_cycled_spin.hpp"

#include <cmath>
#include <string>

namespace needle_sim {

std::vector<NeedleMotionKey> expandDutyCycledSpin(const std::vector<NeedleMotionKey>& keys, const BasePose& rest) {
  const BaseTrajectory shape(rest);  // for the segment's interpolation only
  std::vector<NeedleMotionKey> out;
  double turned = 0;  // added to every later roll
  for (size_t i = 0; i < keys.size(); ++i) {
    NeedleMotionKey a = keys[i];
    if (!(a.spin_duty >= 0 && a.spin_duty <= 1))
      throw std::invalid_argument("spin duty must be in [0, 1], got " + std::to_string(a.spin_duty));
    if (!(std::isfinite(a.spin_rate) && a.spin_rate >= 0))
      throw std::invalid_argument("spin rate must be finite and >= 0, got " + std::to_string(a.spin_rate));
    if (a.spin_duty > 0 && !(a.spin_rate > 0)) throw std::invalid_argument("a spin duty > 0 needs a spin rate > 0");
    const double duty = a.spin_duty, rate = a.spin_rate;
    a.spin_duty = a.spin_rate = 0;
    a.roll += turned;
    out.push_back(a);
    if (duty <= 0 || i + 1 == keys.size()) continue;
    const NeedleMotionKey& b = keys[i + 1];
    const double T = b.t - a.t;
    const int N = std::max(1, static_cast<int>(std::lround(duty * T * rate / (2 * M_PI))));
    const BasePose pa{a.position, a.direction, a.roll}, pb{b.position, b.direction, b.roll + turned};
    auto key = [&](double s, double extra) {
      const BasePose p = shape.interpolate(pa, pb, s);
      NeedleMotionKey k;
      k.t = a.t + s * T;
      k.position = p.position;
      k.direction = p.direction;
      k.roll = p.roll + extra;
      return k;
    };
    for (int c = 0; c < N; ++c) {
      // End of this cycle's turn, then (unless the cycle is all turning) end of its hold.
      const double s_turn = (c + duty) / N, s_end = (c + 1.0) / N;
      if (s_turn < 1) out.push_back(key(s_turn, 2 * M_PI * (c + 1)));
      if (c + 1 < N && duty < 1) out.push_back(key(s_end, 2 * M_PI * (c + 1)));  // (duty 1: no hold)
    }
    turned += 2 * M_PI * N;
  }
  return out;
}

}  // namespace needle_sim
