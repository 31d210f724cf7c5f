#include "needle_sim/needle/scene_trajectory.hpp"

#include "needle_sim/needle/duty_cycled_spin.hpp"

namespace needle_sim {

BaseTrajectory sceneTrajectory(const NeedleParameters& n) {
  BaseTrajectory t(BasePose{n.base_position, n.base_direction, n.base_roll});
  for (const auto& k : expandDutyCycledSpin(n.motion, t.rest())) t.add(k.t, BasePose{k.position, k.direction, k.roll});
  return t;
}

}  // namespace needle_sim
