// Tutorial 0: needle_sim as a C++ library (doc/tutorials/00_library.md). Loads the phantom
// insertion, steps it for 0.5 s, reads what every consumer reads (observables), then asks
// "where will the tip, the target and the holder force be if the base advances 5 mm more?"
// on a copy of the simulation. Built and run by CTest (tutorial_00_library).
#include <cstdio>
#include <string>

#include "needle_sim/core/error.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/prediction.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

int main(int argc, char** argv) {
  const std::string file = argc > 1 ? argv[1] : "config/scenes/phantom_insertion_8x4x4.yaml";
  try {
    // 1. A scene file (and --set style overrides: here a target 2 cm into the phantom).
    const Scene scene = loadScene(file, {"targets=[{name: lesion, point: [0.02, 0.01, 0.01]}]"});
    Simulation sim(scene);
    std::printf("%s: %d DOFs, dt %g s\n", scene.name.c_str(), sim.numDofs(), sim.dt());

    // 2. Step: the scene's own motion drives the needle (a robot would command it through
    //    command/command_guard.hpp, as the node does).
    while (sim.time() < 0.5 - 1e-12) sim.step();

    // 3. Observables: positions, the force on the holder (in the needle's base frame, x along
    //    the needle: the axial force, negative while the tissue resists), insertion state,
    //    targets; computed once, here, for every consumer.
    const Observables o = observe(sim);
    const NeedleObservation& n = o.needles[0];
    std::printf("t = %.3f s: tip (%.4f, %.4f, %.4f) m, %s, axial holder force %.4f N, %d constraint points\n",
                o.time, n.tip.x(), n.tip.y(), n.tip.z(), toString(n.state), n.axial_force, n.constraints);
    std::printf("target 'lesion' moved %.3e m; tip-target distance %.4f m\n", o.targets[0].displacement.norm(),
                o.targets[0].tip_distances[0]);

    // 4. Predict a plan on a copy (the live simulation is not touched): 5 mm more over 0.5 s.
    const BasePose now = sim.needle(0).trajectory().pose(sim.time());
    BasePose ahead = now;
    ahead.position += 0.005 * now.direction;
    InsertionPlan plan;
    plan.waypoints = {{0.5, ahead}};
    plan.duration = 0.6;
    plan.dt = 0.01;  // coarser than the live 1 ms: faster than real time
    const Prediction p = predictInsertion(sim, plan);
    const PredictionSample& end = p.samples.back();
    std::printf("predicted after %.2f s: tip-target %.4f m, holder force (%.4f, %.4f, %.4f) N, %d steps in %.1f ms\n",
                end.t, end.tip_distances[0], end.base_forces[0].x(), end.base_forces[0].y(), end.base_forces[0].z(),
                p.steps, p.copy_ms + p.run_ms);
    std::printf("live simulation still at t = %.3f s\n", sim.time());
    return end.tip_distances[0] < o.targets[0].tip_distances[0] ? 0 : 1;  // the plan brings the tip closer
  } catch (const InputError& e) {
    std::fprintf(stderr, "invalid input: %s\n", e.what());
    return 2;
  } catch (const NumericalError& e) {
    std::fprintf(stderr, "numerical failure: %s\n", e.what());
    return 3;
  }
}
