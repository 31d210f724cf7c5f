#pragma once
// The base's motion a scene gives a needle: its keyframes, duty-cycled spins expanded
// (duty_cycled_spin.hpp). A NeedleBody starts with it; the pre-flight gives it back to a copy
// whose needle waits for commands instead (sim/preflight.hpp).
#include "needle_sim/needle/base_trajectory.hpp"
#include "needle_sim/needle/needle_parameters.hpp"

namespace needle_sim {

BaseTrajectory sceneTrajectory(const NeedleParameters& needle);

}  // namespace needle_sim
