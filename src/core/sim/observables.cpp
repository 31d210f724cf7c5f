#include "needle_sim/sim/observables.hpp"

#include "needle_sim/command/pose_convention.hpp"
#include "needle_sim/needle/tip_path.hpp"
#include "needle_sim/sim/simulation.hpp"

namespace needle_sim {

void observe(const Simulation& sim, Observables& o) {
  o.step = sim.stepIndex();
  o.time = sim.time();
  o.dofs = sim.numDofs();
  o.tissue_dofs = sim.hasTissue() ? sim.tissue().mesh().numDofs() : 0;
  o.tissue_elements = sim.hasTissue() ? sim.tissue().mesh().numElements() : 0;
  o.kinetic_energy = sim.kineticEnergy();
  o.stats = sim.lastStats();
  o.probe_displacement.resize(sim.numProbes());
  for (int i = 0; i < sim.numProbes(); ++i) o.probe_displacement[i] = sim.probeDisplacement(i);

  const int nn = sim.numNeedles();
  o.needles.resize(nn);
  const NeedleTissueInteraction* in = sim.interaction();
  for (int i = 0; i < nn; ++i) {
    const NeedleBody& nd = sim.needle(i);
    NeedleObservation& n = o.needles[i];
    n.tip = nd.tipPosition();
    n.tip_direction = nd.tipDirection();
    n.tip_frame = nodeFrame(nd, nd.beam().numNodes() - 1);
    n.base = nd.state().p[0];
    n.base_frame = nodeFrame(nd, 0);
    // The body's reaction is what the holder applies to the needle; the sensor reads the
    // opposite.
    n.holder_force = -nd.baseForce();
    n.holder_moment = -nd.baseMoment();
    const Eigen::Quaterniond to_base = n.base_frame.conjugate();
    n.holder_force_base = to_base * n.holder_force;
    n.holder_moment_base = to_base * n.holder_moment;
    n.axial_force = n.holder_force_base.x();
    n.state = in ? in->state(i) : InsertionState::Approaching;
    // A released tip whose base has held still (within kHeldStill) is still in: an electrode
    // left in the tissue while the cannula is withdrawn backs off by micrometres as the
    // tissue relaxes; it has not been withdrawn.
    if (n.state == InsertionState::Withdrawing && in->withdrawnSinceRelease(i) < kHeldStill)
      n.state = InsertionState::Inserted;
    n.constraints = in ? in->activePoints(i) : 0;
    n.puncture_force = in ? in->punctureForce(i) : std::numeric_limits<double>::quiet_NaN();
    if (in) {
      const std::vector<Vec3>& path = in->cutPath(i);
      n.path_length = pathLength(path);
      n.path_curvature = endCurvature(path, kPathCurvatureWindow);
    }
    n.bevel_direction = nd.bevel().enabled ? nd.bevelDirection() : Vec3::Zero();
  }

  const int nt = sim.numTargets();
  o.targets.resize(nt);
  const std::vector<TargetError>* errs = sim.lastTargetErrors();
  const long error_step = sim.lastTargetErrorStep();
  for (int i = 0; i < nt; ++i) {
    TargetObservation& t = o.targets[i];
    t.position = sim.targetPosition(i);
    t.velocity = sim.targetVelocity(i);
    t.displacement = t.position - sim.targetStart(i);
    t.shift = t.position - sim.targetRest(i);
    t.tip_distances.resize(nn);
    for (int k = 0; k < nn; ++k) t.tip_distances[k] = (o.needles[k].tip - t.position).norm();
    t.has_error = errs && i < static_cast<int>(errs->size()) && (*errs)[i].valid;
    if (t.has_error) {
      t.error_step = error_step;
      t.error = (*errs)[i].estimate;
      t.error_bound = (*errs)[i].bound;
      t.qoi = (*errs)[i].qoi;
    }
  }

  const ErrorEstimate* e = sim.lastEstimate();
  o.has_estimate = e != nullptr;
  o.eta_global = e ? e->global : 0.0;
  o.eta_max = e ? e->max : 0.0;
  o.eta_relative = e && e->energy > 0 ? e->global / e->energy : 0.0;
}

Observables observe(const Simulation& sim) {
  Observables o;
  observe(sim, o);
  return o;
}

ObservableNames observableNames(const Simulation& sim) {
  ObservableNames l;
  l.scene = sim.scene().name;
  for (int i = 0; i < sim.numNeedles(); ++i) {
    l.needles.push_back(sim.needle(i).name());
    l.needle_radius.push_back(sim.scene().needles[i].radius);
  }
  for (int i = 0; i < sim.numProbes(); ++i) {
    l.probes.push_back(sim.probeName(i));
    l.probe_rest.push_back(sim.scene().probes[i].point);
  }
  for (int i = 0; i < sim.numTargets(); ++i) {
    l.targets.push_back(sim.targetName(i));
    l.target_rest.push_back(sim.targetRest(i));
    l.target_start.push_back(sim.targetStart(i));
  }
  return l;
}

}  // namespace needle_sim
