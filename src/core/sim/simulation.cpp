#include "needle_sim/sim/simulation.hpp"

#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

HexMesh buildTissueMesh(const TissueScene& t) {
  if (t.geometry.kind == TissueGeometry::Kind::Box)
    return HexMesh::box(t.geometry.box.min, t.geometry.box.max, t.cells);
  return HexMesh::mappedBlock(t.geometry.corners, t.cells);
}

Simulation::Simulation(const Scene& scene) : scene_(scene) {
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
}

Vec3 Simulation::probeDisplacement(int i) const {
  const auto& ep = probes_[i];
  return ep.interpolate(tissue_->mesh(), tissue_->positions()) - ep.rest;
}

void Simulation::checkState() const {
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
    last_ = scene_.solver.mode == SolverScene::Mode::Dynamic ? tissue_->stepDynamic(scene_.dt)
                                                             : tissue_->solveStatic();
  } catch (const NumericalError& e) {
    throw NumericalError(k, std::string(e.what()) + " (step " + std::to_string(k) + ")");
  }
  step_ = k;
  checkState();
  return last_;
}

}  // namespace needle_sim
