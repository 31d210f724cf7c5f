#include "needle_sim/io/run_recorder.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <nlohmann/json.hpp>
#include <limits>
#include <numeric>
#include <stdexcept>

#include "needle_sim/io/vtu_writer.hpp"

namespace needle_sim {

namespace fs = std::filesystem;

RunRecorder::RunRecorder(const Simulation& sim, const std::string& dir, const Options& options)
    : sim_(sim), options_(options), step_ms_(1e3 * sim.dt()) {
  dir_ = dir;
  estimate_ = sim.hasTissue() && (options.error_estimate || sim.adaptation());
  target_error_ = sim.hasTissue() && sim.numTargets() > 0 &&
                  (options.target_error ||
                   (sim.adaptation() && sim.adaptation()->settings().estimator == AdaptivitySettings::Estimator::Goal));
  std::error_code ec;
  fs::create_directories(dir_, ec);
  if (ec) throw std::runtime_error("cannot create output directory '" + dir_ + "': " + ec.message());
  for (const char* f : {"summary.json", "timeseries.csv", "timeseries.partial.csv", "centerline.csv",
                        "centerline.partial.csv", "wrench.csv", "wrench.partial.csv", "tissue.vtu", "surface.vtp", "tissue.pvd", "needles.pvd",
                        "surface.pvd"})
    fs::remove(fs::path(dir_) / f, ec);
  if (options.centerline && sim.numNeedles() > 0) {
    centerline_.open(fs::path(dir_) / "centerline.partial.csv");
    centerline_ << "step,t,needle,node,s,x,y,z\n" << std::setprecision(10);
  }
  if (!(options.wrench_rate >= 0) || !std::isfinite(options.wrench_rate))
    throw std::runtime_error("the wrench rate must be a finite number >= 0 [Hz]");
  if (options.wrench_rate > 0 && sim.numNeedles() > 0) {
    wrench_.open(fs::path(dir_) / "wrench.partial.csv");
    wrench_ << "t,between";
    for (int i = 0; i < sim.numNeedles(); ++i)
      for (const char* c : {"fx", "fy", "fz", "mx", "my", "mz"}) wrench_ << ',' << sim.needle(i).name() << '_' << c;
    wrench_ << '\n' << std::setprecision(10);
    wrench_models_.resize(sim.numNeedles());
  }
  if (options.vtu_every > 0) {
    fs::remove_all(fs::path(dir_) / "vtu", ec);
    fs::create_directories(fs::path(dir_) / "vtu", ec);
    if (ec) throw std::runtime_error("cannot create " + dir_ + "/vtu: " + ec.message());
    writeSeriesStep();  // the initial state
  }
  declareColumns();
  csv_.open(fs::path(dir_) / "timeseries.partial.csv");
  if (!csv_) throw std::runtime_error("cannot write to output directory '" + dir_ + "'");
  for (size_t i = 0; i < columns_.size(); ++i) csv_ << (i ? "," : "") << columns_[i].name;
  csv_ << '\n' << std::setprecision(10);
}

// Every column of timeseries.csv, declared once: its name and how a row gets its value
// (from the step's observables, its statistics and its wall time).
void RunRecorder::declareColumns() {
  auto col = [&](std::string name, Writer w) { columns_.push_back({std::move(name), std::move(w)}); };
  auto vec = [&](const std::string& prefix, std::function<Vec3(const Row&)> v) {
    const char* axes[3] = {"x", "y", "z"};
    for (int d = 0; d < 3; ++d) col(prefix + axes[d], [v, d](std::ostream& o, const Row& r) { o << v(r)[d]; });
  };
  col("step", [](std::ostream& o, const Row& r) { o << r.obs.step; });
  col("t", [](std::ostream& o, const Row& r) { o << r.obs.time; });
  col("dofs", [](std::ostream& o, const Row& r) { o << r.obs.dofs; });
  col("step_ms", [](std::ostream& o, const Row& r) { o << r.ms; });
  col("forces_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.forces_ms; });
  col("assemble_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.assemble_ms; });
  col("factor_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.factor_ms; });
  col("solve_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.solve_ms; });
  col("linear_iterations", [](std::ostream& o, const Row& r) { o << r.obs.stats.linear_iterations; });
  col("factorizations", [](std::ostream& o, const Row& r) { o << r.obs.stats.factorizations; });
  col("newton_iterations", [](std::ostream& o, const Row& r) { o << r.obs.stats.newton_iterations; });
  col("kinetic_energy", [](std::ostream& o, const Row& r) { o << r.obs.kinetic_energy; });
  for (int i = 0; i < sim_.numProbes(); ++i)
    vec(sim_.probeName(i) + "_u", [i](const Row& r) { return r.obs.probe_displacement[i]; });
  const bool interaction = sim_.interaction() != nullptr;
  for (int i = 0; i < sim_.numNeedles(); ++i) {
    const std::string n = sim_.needle(i).name() + "_";
    vec(n + "tip_", [i](const Row& r) { return r.obs.needles[i].tip; });
    vec(n + "dir_", [i](const Row& r) { return r.obs.needles[i].tip_direction; });
    // holder_f, holder_m: the needle's force and moment on its holder (a force/torque
    // sensor's reading), tissue frame; axial_force: its component along the needle, negative
    // when the tissue resists the insertion (observables.hpp).
    vec(n + "holder_f", [i](const Row& r) { return r.obs.needles[i].holder_force; });
    vec(n + "holder_m", [i](const Row& r) { return r.obs.needles[i].holder_moment; });
    col(n + "axial_force", [i](std::ostream& o, const Row& r) { o << r.obs.needles[i].axial_force; });
    if (interaction) {
      col(n + "state", [i](std::ostream& o, const Row& r) { o << toString(r.obs.needles[i].state); });
      col(n + "constraints", [i](std::ostream& o, const Row& r) { o << r.obs.needles[i].constraints; });
      if (sim_.needle(i).bevel().enabled) {
        // Steering: the cut path's length and bending (observables.hpp), the bevel's direction.
        col(n + "path_length", [i](std::ostream& o, const Row& r) { o << r.obs.needles[i].path_length; });
        col(n + "path_curvature", [i](std::ostream& o, const Row& r) { o << r.obs.needles[i].path_curvature; });
        vec(n + "bevel_", [i](const Row& r) { return r.obs.needles[i].bevel_direction; });
      }
    }
  }
  if (interaction) {
    col("constraint_points", [](std::ostream& o, const Row& r) { o << r.obs.stats.constraint_points; });
    col("constraint_iterations", [](std::ostream& o, const Row& r) { o << r.obs.stats.constraint_iterations; });
    col("constraint_residual", [](std::ostream& o, const Row& r) { o << r.obs.stats.constraint_residual; });
    col("constraint_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.constraint_ms; });
  }
  // Targets: position, displacement from the planning (rest) position, distance to each tip.
  for (int i = 0; i < sim_.numTargets(); ++i) {
    const std::string n = sim_.targetName(i) + "_";
    vec(n, [i](const Row& r) { return r.obs.targets[i].position; });
    vec(n + "u", [i](const Row& r) { return r.obs.targets[i].shift; });
    col(n + "u", [i](std::ostream& o, const Row& r) { o << r.obs.targets[i].shift.norm(); });
    for (int k = 0; k < sim_.numNeedles(); ++k)
      col(n + "dist_" + sim_.needle(k).name(),
          [i, k](std::ostream& o, const Row& r) { o << r.obs.targets[i].tip_distances[k]; });
  }
  if (target_error_)
    for (int i = 0; i < sim_.numTargets(); ++i) {
      const std::string n = sim_.targetName(i) + "_";
      const double nan = std::numeric_limits<double>::quiet_NaN();
      vec(n + "err_", [i, nan](const Row& r) { return r.obs.targets[i].has_error ? r.obs.targets[i].error : Vec3::Constant(nan); });
      col(n + "err_bound", [i, nan](std::ostream& o, const Row& r) {
        o << (r.obs.targets[i].has_error ? r.obs.targets[i].error_bound : nan);
      });
      vec(n + "qoi_", [i, nan](const Row& r) { return r.obs.targets[i].has_error ? r.obs.targets[i].qoi : Vec3::Constant(nan); });
    }
  if (estimate_) {
    // With --error-estimate every step; otherwise (adaptivity) the last pass's estimate.
    col("eta_global", [](std::ostream& o, const Row& r) { o << r.obs.eta_global; });
    col("eta_max", [](std::ostream& o, const Row& r) { o << r.obs.eta_max; });
    col("eta_relative", [](std::ostream& o, const Row& r) { o << r.obs.eta_relative; });
  }
  if (const auto* a = sim_.adaptation()) {
    col("tissue_elements", [](std::ostream& o, const Row& r) { o << r.obs.tissue_elements; });
    for (int l = 0; l <= a->settings().max_level; ++l)
      col("elements_L" + std::to_string(l), [this, l](std::ostream& o, const Row&) {
        const auto per = sim_.elementsPerLevel();
        o << (l < static_cast<int>(per.size()) ? per[l] : 0);
      });
    col("refined", [](std::ostream& o, const Row& r) { o << r.obs.stats.refined; });
    col("coarsened", [](std::ostream& o, const Row& r) { o << r.obs.stats.coarsened; });
    col("estimate_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.estimate_ms; });
    col("mark_refine_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.mark_refine_ms; });
    col("rebuild_ms", [](std::ostream& o, const Row& r) { o << r.obs.stats.rebuild_ms; });
  }
}

void RunRecorder::recordStep(const StepStats& s, double ms) {
  if (options_.error_estimate && sim_.hasTissue()) sim_.errorEstimate();  // every step, asked for
  if (options_.target_error && target_error_ && sim_.stepIndex() % std::max(1, options_.target_error_every) == 0)
    sim_.targetErrors();
  observe(sim_, obs_);
  obs_.stats = s;
  const Row row{obs_, ms};
  for (size_t i = 0; i < columns_.size(); ++i) {
    if (i) csv_ << ',';
    columns_[i].write(csv_, row);
  }
  csv_ << '\n';

  step_ms_.add(ms);
  forces_ms_.add(s.forces_ms);
  assemble_ms_.add(s.assemble_ms);
  factor_ms_.add(s.factor_ms);
  solve_ms_.add(s.solve_ms);
  linear_iterations_ += s.linear_iterations;
  factorizations_ += s.factorizations;
  async_factorizations_ += s.async_factorizations;
  factor_waits_ += s.factor_waits;
  factor_wait_ms_max_ = std::max(factor_wait_ms_max_, s.factor_wait_ms);
  newton_iterations_ += s.newton_iterations;
  max_linear_iterations_ = std::max(max_linear_iterations_, s.linear_iterations);
  max_linear_residual_ = std::max(max_linear_residual_, s.linear_residual);
  if (wrench_.is_open()) writeWrenches();
  for (int i = 0; i < sim_.numNeedles(); ++i) {
    if (!centerline_.is_open()) break;
    const auto& nd = sim_.needle(i);
    for (int k = 0; k < nd.beam().numNodes(); ++k) {
      const Vec3& p = nd.state().p[k];
      centerline_ << obs_.step << ',' << obs_.time << ',' << nd.name() << ',' << k << ','
                  << k * nd.beam().elementLength() << ',' << p[0] << ',' << p[1] << ',' << p[2] << '\n';
    }
  }
  for (int i = 0; i < sim_.numTargets(); ++i)
    for (int k = 0; k < sim_.numNeedles(); ++k) {
      auto& m = min_target_distance_[sim_.targetName(i) + "/" + sim_.needle(k).name()];
      m = std::min(m == 0 ? 1e300 : m, obs_.targets[i].tip_distances[k]);
    }
  if (estimate_ && obs_.has_estimate) {
    eta_last_ = obs_.eta_global;
    eta_max_last_ = obs_.eta_max;
    eta_rel_max_ = std::max(eta_rel_max_, obs_.eta_relative);
  }
  if (sim_.adaptation()) {
    adapt_ms_.add(s.adapt_ms());
    mesh_changes_ += s.mesh_changed;
    refined_total_ += s.refined;
    coarsened_total_ += s.coarsened;
  }
  if (sim_.hasTissue()) max_tissue_dofs_ = std::max(max_tissue_dofs_, obs_.tissue_dofs);
  constraint_iterations_ += s.constraint_iterations;
  max_constraint_points_ = std::max(max_constraint_points_, s.constraint_points);
  max_constraint_residual_ = std::max(max_constraint_residual_, s.constraint_residual);
  constraint_unconverged_ += s.constraint_converged ? 0 : 1;
  constraint_ms_.add(s.constraint_ms);
  if (options_.vtu_every > 0 && obs_.step % options_.vtu_every == 0) writeSeriesStep();
}

void RunRecorder::writeSeriesStep() {
  char name[64];
  const long k = sim_.stepIndex();
  const double t = sim_.time();
  if (sim_.hasTissue()) {
    const auto& body = sim_.tissue();
    const ErrorEstimate& est = sim_.errorEstimate();
    VtuCellData cells;
    for (const auto& sgm : est.centroid_stress) cells.von_mises.push_back(SprEstimator::vonMises(sgm));
    cells.eta = est.eta;
    cells.level = sim_.elementLevels();
    std::snprintf(name, sizeof name, "vtu/tissue_%06ld.vtu", k);
    writeVtu((fs::path(dir_) / name).string(), body.mesh(), body.positions(), cells);
    series_tissue_.emplace_back(t, name);
    if (const auto* organ = sim_.organSurface()) {
      std::vector<Vec3> p;
      organ->positions(body.positions(), p);
      std::snprintf(name, sizeof name, "vtu/surface_%06ld.vtp", k);
      writeSurfaceVtp((fs::path(dir_) / name).string(), organ->rest(), p);
      series_surface_.emplace_back(t, name);
    }
  }
  if (sim_.numNeedles() > 0) {
    std::vector<std::vector<Vec3>> lines;
    for (int i = 0; i < sim_.numNeedles(); ++i) lines.push_back(sim_.needle(i).state().p);
    std::snprintf(name, sizeof name, "vtu/needles_%06ld.vtp", k);
    writeCentreLinesVtp((fs::path(dir_) / name).string(), lines);
    series_needles_.emplace_back(t, name);
  }
  writeSeriesIndex();  // kept current: a failed run still opens up to its last written step
}

void RunRecorder::writeSeriesIndex() const {
  if (!series_tissue_.empty()) writePvd((fs::path(dir_) / "tissue.pvd").string(), series_tissue_);
  if (!series_needles_.empty()) writePvd((fs::path(dir_) / "needles.pvd").string(), series_needles_);
  if (!series_surface_.empty()) writePvd((fs::path(dir_) / "surface.pvd").string(), series_surface_);
}

void RunRecorder::writeSummary(const std::string& status, double wall_s, long fail_step, const std::string& message) {
  using nlohmann::json;
  const auto& scene = sim_.scene();
  json j;
  j["status"] = status;
  if (status != "ok") {
    j["failed_step"] = fail_step;
    j["message"] = message;
  }
  j["scene"] = {{"name", scene.name}, {"file", scene.file}, {"description", scene.description}};
  j["mode"] = scene.solver.mode == SolverSettings::Mode::Dynamic ? "dynamic" : "static";
  j["dofs"] = sim_.numDofs();
  j["elements"] = sim_.numElements();
  if (sim_.hasTissue()) {
    const auto& body = sim_.tissue();
    j["tissue"] = {{"dofs", body.mesh().numDofs()},
                   {"free_dofs", body.dofs().numFree()},
                   {"nodes", body.mesh().numNodes()},
                   {"elements", body.mesh().numElements()},
                   {"inverted_elements", body.model().invertedElements()}};
  }
  // The final state's figures from the observables (the same numbers as the last row of
  // timeseries.csv); names in scene order (JSON objects sort their keys).
  const Observables o = observe(sim_);
  const ObservableNames names = observableNames(sim_);
  j["names"] = {{"needles", names.needles}, {"probes", names.probes}, {"targets", names.targets}};
  json needles = json::object();
  auto arr = [](const Vec3& v) { return json::array({v[0], v[1], v[2]}); };
  for (int i = 0; i < sim_.numNeedles(); ++i) {
    const auto& nd = sim_.needle(i);
    const NeedleObservation& n = o.needles[i];
    needles[nd.name()] = {{"elements", nd.beam().numElements()},
                          {"dofs", nd.numDofs()},
                          {"tip", arr(n.tip)},
                          {"direction", arr(n.tip_direction)},
                          {"holder_force", arr(n.holder_force)},
                          {"holder_moment", arr(n.holder_moment)},
                          {"axial_force", n.axial_force},
                          {"elastic_energy", nd.elasticEnergy()}};
    json line = json::array();
    for (const auto& p : nd.state().p) line.push_back(arr(p));
    needles[nd.name()]["centerline"] = line;
    if (const auto* in = sim_.interaction()) {
      needles[nd.name()]["state"] = toString(n.state);
      needles[nd.name()]["constraints"] = n.constraints;
      needles[nd.name()]["puncture_force"] = std::isnan(n.puncture_force) ? json(nullptr) : json(n.puncture_force);
      // The cut path in rest (material) space, from the puncture to the tip's last anchor.
      json path = json::array();
      for (const auto& p : in->cutPath(i)) path.push_back(arr(p));
      needles[nd.name()]["cut_path"] = path;
      needles[nd.name()]["cut_path_length"] = n.path_length;
    }
  }
  if (sim_.numNeedles()) j["needles"] = needles;
  j["steps"] = sim_.stepIndex();
  j["dt"] = scene.dt;
  j["time"] = sim_.time();
  j["wall_time_s"] = wall_s;
  auto pj = [](const Percentiles& p) {
    return json{{"median", p.median}, {"p95", p.p95}, {"p99", p.p99}, {"p999", p.p999}, {"max", p.max}, {"mean", p.mean}};
  };
  j["step_ms"] = pj(step_ms_.percentiles());
  // Deadlines of a real-time run at this dt: steps that took longer than dt, and the longest
  // run of them in a row.
  j["step_ms"]["deadline_ms"] = step_ms_.deadline();
  j["step_ms"]["deadline_misses"] = step_ms_.misses();
  j["step_ms"]["longest_miss_run"] = step_ms_.longestMissRun();
  j["split_ms"] = {{"forces", pj(forces_ms_.percentiles())},
                   {"assemble", pj(assemble_ms_.percentiles())},
                   {"factor", pj(factor_ms_.percentiles())},
                   {"solve", pj(solve_ms_.percentiles())}};
  j["solver"] = {{"method", scene.solver.linear.method == LinearSolverSettings::Method::Pcg ? "pcg" : "direct"},
                 {"linear_iterations_total", linear_iterations_},
                 {"linear_iterations_max", max_linear_iterations_},
                 {"linear_residual_max", max_linear_residual_},
                 {"factorizations", factorizations_},
                 {"async", scene.solver.linear.async},
                 {"async_lag", scene.solver.linear.async_lag},
                 {"async_factorizations", async_factorizations_},
                 {"factor_waits", factor_waits_},
                 {"factor_wait_ms_max", factor_wait_ms_max_},
                 {"newton_iterations_total", newton_iterations_}};
  if (estimate_)
    j["error_estimate"] = {{"eta_global", eta_last_}, {"eta_max", eta_max_last_}, {"eta_relative_max", eta_rel_max_}};
  if (const auto* a = sim_.adaptation()) {
    double total_adapt = adapt_ms_.sum();
    double total_step = step_ms_.sum();
    j["adaptivity"] = {{"tissue_dofs_final", sim_.tissue().mesh().numDofs()},
                       {"tissue_dofs_max", max_tissue_dofs_},
                       {"elements_per_level", sim_.elementsPerLevel()},
                       {"hanging_nodes", sim_.hangingNodes()},
                       {"rebuild_delay_s", a->settings().rebuild_delay},
                       {"deferred_mesh_changes", sim_.adaptationCounters().deferred_rebuilds},
                       {"rebuild_waits", sim_.adaptationCounters().rebuild_waits},
                       {"estimate_delay_s", a->settings().estimate_delay},
                       {"background_passes", sim_.adaptationCounters().background_passes},
                       {"pass_waits", sim_.adaptationCounters().pass_waits},
                       {"passes_after_decision", sim_.adaptationCounters().passes_after_decision},
                       {"ahead_marked", sim_.adaptationCounters().ahead_marked},
                       {"mesh_changes", mesh_changes_},
                       {"cells_refined_total", refined_total_},
                       {"cells_coarsened_total", coarsened_total_},
                       {"adapt_ms", pj(adapt_ms_.percentiles())},
                       {"adapt_share_of_run", total_step > 0 ? total_adapt / total_step : 0.0}};
  }
  if (sim_.interaction())
    j["interaction"] = {{"constraint_iterations_total", constraint_iterations_},
                        {"constraint_points_max", max_constraint_points_},
                        {"constraint_residual_max", max_constraint_residual_},
                        {"unconverged_steps", constraint_unconverged_},
                        {"constraint_ms", pj(constraint_ms_.percentiles())}};
  j["energy"] = {{"kinetic", sim_.kineticEnergy()}, {"elastic", sim_.elasticEnergy()}};
  json probes = json::object();
  for (int i = 0; i < sim_.numProbes(); ++i) {
    const Vec3& u = o.probe_displacement[i];
    const Vec3& p = names.probe_rest[i];
    probes[sim_.probeName(i)] = {{"point", {p[0], p[1], p[2]}}, {"displacement", {u[0], u[1], u[2]}}, {"norm", u.norm()}};
  }
  j["probes"] = probes;
  if (sim_.numTargets()) {
    json targets = json::object();
    for (int i = 0; i < sim_.numTargets(); ++i) {
      const TargetObservation& ot = o.targets[i];
      json t = {{"planned", arr(names.target_rest[i])},
                {"position", arr(ot.position)},
                {"displacement", arr(ot.shift)},
                {"displacement_norm", ot.shift.norm()},
                {"motion_since_start", ot.displacement.norm()}};
      if (target_error_) {
        const auto* errs = sim_.lastTargetErrors();
        if (errs && i < static_cast<int>(errs->size()) && (*errs)[i].valid) {
          const TargetError& e = (*errs)[i];
          t["error_estimate"] = arr(e.estimate);
          t["error_bound"] = e.bound;
          t["error_component_bound"] = arr(e.component_bound);
          t["error_bound_global"] = e.global_bound;
          t["qoi"] = arr(e.qoi);
          t["qoi_radius"] = sim_.qoiRadius(i);
          t["error_step"] = sim_.lastTargetErrorStep();
          t["eta_energy"] = e.eta_u;
          t["eta_dual"] = arr(e.eta_z);
        } else {
          t["error_estimate"] = nullptr;
          t["error_bound"] = nullptr;
        }
      }
      for (int k = 0; k < sim_.numNeedles(); ++k) {
        const std::string& nn = names.needles[k];
        t["tip_distance"][nn] = ot.tip_distances[k];
        auto it = min_target_distance_.find(sim_.targetName(i) + "/" + nn);
        if (it != min_target_distance_.end()) t["tip_distance_min"][nn] = it->second;
      }
      targets[sim_.targetName(i)] = t;
    }
    j["targets"] = targets;
  }
  if (const auto* g = sim_.immersedGrid()) {
    j["immersed"] = {{"surface", scene.tissue.geometry.surface_file},
                     {"surface_volume", scene.tissue.geometry.surface->volume()},
                     {"grid_volume", g->volume()},
                     {"grid_cells", {g->dims()[0], g->dims()[1], g->dims()[2]}},
                     {"cell_size", arr(g->cellSize())},
                     {"kept_cells", g->mesh().numElements()},
                     {"defective_rays", g->insideTest().defectiveRays()}};
  }
  const auto& bs = sim_.brainShift();
  if (bs.done) {
    j["brain_shift"] = {{"load_scale", bs.load_scale},
                        {"max_displacement", bs.max_displacement},
                        {"load_solves", bs.load_solves},
                        {"newton_iterations", bs.newton_iterations},
                        {"multiplier_updates", bs.multiplier_updates},
                        {"restarts", bs.restarts},
                        {"factorizations", bs.factorizations},
                        {"skull_contacts", bs.contacts},
                        {"skull_max_penetration", bs.max_penetration},
                        {"skull_force", bs.skull_force},
                        {"skull_support", sim_.scene().brain_shift->skull_support},
                        {"passes", bs.passes},
                        {"dofs", bs.dofs},
                        {"ms", bs.ms}};
    if (bs.coarse_dofs > 0)  // brain_shift.coarse_start: its share of the figures above
      j["brain_shift"]["coarse_start"] = {{"dofs", bs.coarse_dofs},
                                          {"newton_iterations", bs.coarse_newton_iterations},
                                          {"factorizations", bs.coarse_factorizations},
                                          {"load_scale", bs.coarse_load_scale},
                                          {"ms", bs.coarse_ms}};
    if (!bs.target.empty()) {
      j["brain_shift"]["target"] = bs.target;
      j["brain_shift"]["target_displacement"] = arr(bs.target_displacement);
      j["brain_shift"]["target_shift"] = bs.target_displacement.norm();
    }
    // The re-aimed trajectories (brain_shift.replan): entry, planned and new final tip.
    for (size_t n = 0; n < sim_.replans().size(); ++n) {
      const TrajectoryReplan& r = sim_.replans()[n];
      j["brain_shift"]["replanned"][sim_.scene().needles[n].name] = {
          {"entry", arr(r.entry)},
          {"planned_tip", arr(r.planned_tip)},
          {"replanned_tip", arr(r.entry + r.scale * (r.rotation * (r.planned_tip - r.entry)))},
          {"angle_rad", r.angle()},
          {"advance_scale", r.scale}};
    }
  }
  const fs::path tmp = fs::path(dir_) / "summary.json.tmp";
  {
    std::ofstream out(tmp);
    out << std::setw(2) << j << '\n';
    if (!out) throw std::runtime_error("cannot write " + tmp.string());
  }
  fs::rename(tmp, fs::path(dir_) / "summary.json");
}

void RunRecorder::writeWrenches() {
  // The step's wrenches (between = 0), then each 1/rate until the next step's time (between =
  // 1): the step's model with the base where its commanded motion has it then.
  const int n = sim_.numNeedles();
  auto row = [&](double t, bool between) {
    wrench_ << t << ',' << (between ? 1 : 0);
    for (int i = 0; i < n; ++i) {
      Vec3 f = obs_.needles[i].holder_force, m = obs_.needles[i].holder_moment;
      if (between) wrench_models_[i].at(sim_.needle(i).trajectory().pose(t).position, f, m);
      wrench_ << ',' << f[0] << ',' << f[1] << ',' << f[2] << ',' << m[0] << ',' << m[1] << ',' << m[2];
    }
    wrench_ << '\n';
  };
  for (int i = 0; i < n; ++i) {
    const NeedleObservation& nd = obs_.needles[i];
    wrench_models_[i].afterStep(sim_.needle(i).trajectory().pose(obs_.time).position, nd.holder_force,
                                nd.holder_moment, nd.constraints);
  }
  row(obs_.time, false);
  const double period = 1 / options_.wrench_rate, next = obs_.time + sim_.dt();
  for (int j = 1; obs_.time + j * period < next - 1e-9 * sim_.dt(); ++j) row(obs_.time + j * period, true);
}

void RunRecorder::finish(double wall_s) {
  csv_.close();
  if (options_.vtu && sim_.hasTissue()) {
    const auto& body = sim_.tissue();
    const ErrorEstimate& est = sim_.errorEstimate();
    VtuCellData cells;
    for (const auto& sgm : est.centroid_stress) cells.von_mises.push_back(SprEstimator::vonMises(sgm));
    cells.eta = est.eta;
    cells.level = sim_.elementLevels();
    writeVtu((fs::path(dir_) / "tissue.vtu").string(), body.mesh(), body.positions(), cells);
    if (const auto* organ = sim_.organSurface()) {
      std::vector<Vec3> p;
      organ->positions(body.positions(), p);
      writeSurfaceVtp((fs::path(dir_) / "surface.vtp").string(), organ->rest(), p);
    }
  }
  fs::rename(fs::path(dir_) / "timeseries.partial.csv", fs::path(dir_) / "timeseries.csv");
  if (centerline_.is_open()) {
    centerline_.close();
    fs::rename(fs::path(dir_) / "centerline.partial.csv", fs::path(dir_) / "centerline.csv");
  }
  if (wrench_.is_open()) {
    wrench_.close();
    fs::rename(fs::path(dir_) / "wrench.partial.csv", fs::path(dir_) / "wrench.csv");
  }
  writeSummary("ok", wall_s, -1, "");
}

void RunRecorder::fail(double wall_s, long step, const std::string& message) {
  csv_.close();
  centerline_.close();
  wrench_.close();
  writeSummary("numerical_failure", wall_s, step, message);
}

}  // namespace needle_sim
