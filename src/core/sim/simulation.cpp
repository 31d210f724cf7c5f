#include "needle_sim/sim/simulation.hpp"

#include <algorithm>
#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& t) {
  if (t.geometry.kind == TissueGeometry::Kind::Box)
    return HexMesh::box(t.geometry.box.min, t.geometry.box.max, t.cells);
  return HexMesh::mappedBlock(t.geometry.corners, t.cells);
}

Simulation::Simulation(const Scene& scene) : scene_(scene) {
  for (const auto& n : scene.needles) needles_.push_back(std::make_unique<NeedleBody>(n, scene.solver));
  if (!scene.has_tissue) return;
  HexMesh mesh;
  try {
    mesh = buildTissueMesh(scene.tissue);
    tissue_ = std::make_unique<TissueBody>(std::move(mesh), scene.tissue, scene.solver, scene.file);
  } catch (const std::invalid_argument& e) {
    throw InputError(scene.file, "tissue.geometry", std::string("invalid mesh: ") + e.what());
  }
  diag_ = (tissue_->mesh().boundsMax() - tissue_->mesh().boundsMin()).norm();
  PointLocator locator(tissue_->mesh());
  for (size_t i = 0; i < scene.probes.size(); ++i) {
    EmbeddedPoint ep;
    if (!locator.locate(scene.probes[i].point, ep)) {
      std::ostringstream m;
      m << "point (" << scene.probes[i].point.transpose() << ") lies outside the tissue";
      throw InputError(scene.file, "probes[" + std::to_string(i) + "].point", m.str());
    }
    probes_.push_back(ep);
  }
  // A needle must start outside the tissue: puncture happens on the surface.
  for (size_t n = 0; n < needles_.size(); ++n)
    for (int i = 0; i < needles_[n]->beam().numNodes(); ++i) {
      EmbeddedPoint ep;
      const Vec3& p = needles_[n]->state().p[i];
      if (locator.locate(p, ep)) {
        std::ostringstream m;
        m << "the needle starts inside the tissue (node " << i << " at (" << p.transpose()
          << ")); place its tip outside the tissue surface";
        throw InputError(scene.file, scene.needles[n].key + ".base.position", m.str());
      }
    }
  if (scene.interaction) {
    std::vector<NeedleBody*> nd;
    for (auto& n : needles_) nd.push_back(n.get());
    interaction_ = std::make_unique<NeedleTissueInteraction>(*scene.interaction, *tissue_, nd);
  }
}

Vec3 Simulation::probeDisplacement(int i) const {
  const auto& ep = probes_[i];
  return ep.interpolate(tissue_->mesh(), tissue_->positions()) - ep.rest;
}

int Simulation::numDofs() const {
  int n = tissue_ ? tissue_->mesh().numDofs() : 0;
  for (const auto& nd : needles_) n += nd->numDofs();
  return n;
}

int Simulation::numElements() const {
  int n = tissue_ ? tissue_->mesh().numElements() : 0;
  for (const auto& nd : needles_) n += nd->beam().numElements();
  return n;
}

double Simulation::kineticEnergy() const {
  double e = tissue_ ? tissue_->kineticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->kineticEnergy();
  return e;
}

double Simulation::elasticEnergy() const {
  double e = tissue_ ? tissue_->elasticEnergy() : 0;
  for (const auto& nd : needles_) e += nd->elasticEnergy();
  return e;
}

void Simulation::checkState() const {
  for (const auto& nd : needles_) {
    for (int i = 0; i < nd->beam().numNodes(); ++i)
      if (!nd->state().p[i].allFinite() || !nd->state().q[i].coeffs().allFinite())
        throw NumericalError(step_, "needle '" + nd->name() + "': non-finite state at step " + std::to_string(step_));
    const double reach = (nd->tipPosition() - nd->state().p[0]).norm();
    if (reach > 2 * nd->beam().length())
      throw NumericalError(step_, "needle '" + nd->name() + "' diverged at step " + std::to_string(step_) +
                                      ": tip " + std::to_string(reach) + " m from the base");
  }
  if (!tissue_) return;
  const VecX& x = tissue_->positions();
  const VecX& v = tissue_->velocities();
  if (!x.allFinite() || !v.allFinite())
    throw NumericalError(step_, "non-finite positions or velocities at step " + std::to_string(step_));
  const double umax = tissue_->displacements().lpNorm<Eigen::Infinity>();
  if (umax > 10 * diag_)
    throw NumericalError(step_, "divergence at step " + std::to_string(step_) + ": displacement " +
                                    std::to_string(umax) + " m exceeds 10x the tissue size");
}

const StepStats& Simulation::step() {
  const long k = step_ + 1;
  try {
    const bool dynamic = scene_.solver.mode == SolverScene::Mode::Dynamic;
    last_ = StepStats{};
    auto add = [&](const StepStats& s) {
      last_.forces_ms += s.forces_ms;
      last_.assemble_ms += s.assemble_ms;
      last_.factor_ms += s.factor_ms;
      last_.solve_ms += s.solve_ms;
      last_.linear_iterations += s.linear_iterations;
      last_.factorizations += s.factorizations;
      last_.linear_residual = std::max(last_.linear_residual, s.linear_residual);
      last_.newton_iterations += s.newton_iterations;
      last_.newton_residual = std::max(last_.newton_residual, s.newton_residual);
    };
    if (interaction_) {
      // free motion of every body, constraint solve and corrections, commit, law updates
      const double h = scene_.dt;
      add(tissue_->freeMotion(h));
      for (auto& nd : needles_) add(nd->freeMotion(time(), h));
      const InteractionStats is = interaction_->solve(h);
      last_.constraint_points = is.points;
      last_.constraint_iterations = is.iterations;
      last_.constraint_residual = is.residual;
      last_.constraint_ms = is.ms;
      tissue_->commit(h);
      for (auto& nd : needles_) nd->commit(time(), h);
      interaction_->afterCommit();
    } else {
      if (tissue_) add(dynamic ? tissue_->stepDynamic(scene_.dt) : tissue_->solveStatic());
      for (auto& nd : needles_) add(dynamic ? nd->stepDynamic(time(), scene_.dt) : nd->solveStatic(k * scene_.dt));
    }
  } catch (const NumericalError& e) {
    throw NumericalError(k, std::string(e.what()) + " (step " + std::to_string(k) + ")");
  }
  step_ = k;
  checkState();
  return last_;
}

}  // namespace needle_sim
