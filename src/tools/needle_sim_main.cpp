// needle_sim: the headless command-line driver of the simulator.
//
// Reference: doc/cli.md. Sample runs:
//   needle_sim run phantom_insertion_adaptive.yaml --out results/adaptive --vtu-every 100
//   needle_sim run config/scenes/phantom_8x4x4.yaml --out results/phantom_8x4x4
//   needle_sim run config/scenes/phantom_8x4x4.yaml --out /tmp/r --set tissue.grid.cells=[16,8,8]
//   needle_sim check config/scenes/cook_membrane.yaml --set tissue.grid.cells=[32,32,1]
//   needle_sim check dbs_coarse.yaml --json --aim -0.036 0.020 0.062 -0.0111 -0.0129 -0.0077
//   needle_sim bench --steps 30
//   needle_sim soak config/scenes/phantom_insertion_adaptive.yaml --steps 100000
//   needle_sim predict config/scenes/phantom_insertion_adaptive.yaml --duration 10 --advance 0.02 --dt 0.01
//   needle_sim calibrate phantom_insertion_8x4x4.yaml --data force.csv --fit interaction.cutting_force --out /tmp/c
//   needle_sim ensemble dbs_coarse.yaml --samples 16 --vary "tissue.material.young=lognormal(6000,2)" --out /tmp/e
//
// Exit status: 0 success, 2 invalid input (scene, overrides, command line),
// 3 numerical failure (NaN/Inf, divergence, solver failure; reported with the step).
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <algorithm>
#include <fstream>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <thread>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <unistd.h>

#include "needle_sim/core/blas_threads.hpp"
#include "needle_sim/core/denormals.hpp"
#include "needle_sim/core/heap_retention.hpp"
#include "needle_sim/calibration/force_record.hpp"
#include "needle_sim/sim/command_replay.hpp"
#include "needle_sim/core/error.hpp"
#include "needle_sim/io/run_recorder.hpp"
#include "needle_sim/scene/scene_keys.hpp"
#include "needle_sim/scene/scene_check.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/observables.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "assimilate.hpp"
#include "bag_input.hpp"
#include "bag_output.hpp"
#include "bench.hpp"
#include "calibrate.hpp"
#include "check.hpp"
#include "predict.hpp"
#include "steer.hpp"
#include "exit_codes.hpp"
#include "share_dir.hpp"
#include "soak.hpp"

using namespace needle_sim;
using needle_sim_tool::kExitInput;
using needle_sim_tool::kExitNumerical;

namespace {


// A recorded session driving the run (run --bag).
struct BagRun {
  std::string bag, pose_topic, wrench_topic, needle;
  // Measurements for --assimilate, as the node's topics take them (bag_input.hpp).
  std::string tip_topic, target_topic, shape_topic, measured_target;
  double shape_spacing = 5e-4;
  std::string out_bag, out_ns = "/needle_sim";  // run --out-bag: the outputs as a bag
  bool given() const { return !bag.empty(); }
};

int runCommand(const std::string& scene_path, const std::string& out_dir, const std::vector<std::string>& sets,
               bool quiet, const RunRecorder::Options& options, const BagRun& bag_run, const AssimilateOptions& assimilate) {
  Scene scene;
  std::unique_ptr<Simulation> sim;
  std::unique_ptr<CommandReplay> replay;
  BagSession session;
  int bag_needle = 0;
  std::unique_ptr<ForceAssimilation> assim;
  try {
    scene = loadScene(scene_path, sets);
    for (const std::string& w : sceneWarnings(scene)) std::cerr << "needle_sim: warning: " << w << '\n';
    if (bag_run.given()) {
      if (bag_run.pose_topic.empty()) throw InputError("", "--pose-topic", "needed with --bag");
      if (scene.needles.empty()) throw InputError(scene_path, "needle", "--bag drives a needle: the scene has none");
      if (!bag_run.needle.empty()) {
        bag_needle = -1;
        for (size_t i = 0; i < scene.needles.size(); ++i)
          if (scene.needles[i].name == bag_run.needle) bag_needle = static_cast<int>(i);
        if (bag_needle < 0) throw InputError(scene_path, "--needle", "no needle named '" + bag_run.needle + "'");
      }
      BagTopics topics;
      topics.pose = bag_run.pose_topic;
      topics.wrench = bag_run.wrench_topic;
      topics.tip = bag_run.tip_topic;
      topics.target = bag_run.target_topic;
      topics.shape = bag_run.shape_topic;
      topics.shape_spacing = bag_run.shape_spacing;
      topics.num_targets = static_cast<int>(scene.targets.size());
      if (!bag_run.target_topic.empty()) {
        if (scene.targets.empty()) throw InputError(scene_path, "--target-topic", "the scene has no target to measure");
        topics.target_index = -1;
        for (size_t j = 0; j < scene.targets.size(); ++j)
          if (bag_run.measured_target.empty() ? j == 0 : scene.targets[j].name == bag_run.measured_target)
            topics.target_index = static_cast<int>(j);
        if (topics.target_index < 0)
          throw InputError(scene_path, "--measured-target", "no target named '" + bag_run.measured_target + "'");
      }
      if (!assimilate.given() && !(topics.tip.empty() && topics.target.empty() && topics.shape.empty()))
        throw InputError("", topics.tip.empty() ? (topics.target.empty() ? "--shape-topic" : "--target-topic") : "--tip-topic",
                         "a measured position or shape is for --assimilate KEYS");
      session = readBagSession(bag_run.bag, topics, bag_needle, scene.needles[bag_needle].length);
      // The recording drives the needle from its rest pose, for as long as it lasts.
      scene.needles[bag_needle].motion.clear();
      scene.duration = std::max(session.end, scene.dt);
    }
    if (options.target_error && scene.targets.empty())
      throw InputError(scene_path, "--target-error", "the scene has no targets to estimate the error of");
    Simulation::Options so;
    so.target_errors = options.target_error;
    sim = std::make_unique<Simulation>(scene, so);
    if (bag_run.given()) replay = std::make_unique<CommandReplay>(*sim, CommandLimits{}, session.commands);
    if (!assimilate.given() && !assimilate.data.empty())
      throw InputError("", "--data", "a measurement is for --assimilate KEYS (calibrate fits offline)");
    if (assimilate.given()) {
      if (scene.needles.empty()) throw InputError(scene_path, "--assimilate", "the scene has no needle whose force could be measured");
      assim = makeAssimilation(assimilate, scene_path, sets, bag_needle, &session.force,
                               bag_run.given() ? &session.commands : nullptr, observableNames(*sim).targets);
    }
  } catch (const InputError& e) {
    std::cerr << "needle_sim: invalid input: " << e.what() << '\n';
    return kExitInput;
  } catch (const NumericalError& e) {
    // A failure while the simulation is built (the brain shift's pre-step): the run's
    // folder says so, as for a failure during the steps.
    std::error_code ec;
    std::filesystem::create_directories(out_dir, ec);
    std::ofstream f(out_dir + "/summary.json");
    f << nlohmann::json{{"status", "numerical_failure"}, {"failed_step", e.step()}, {"message", e.what()},
                        {"scene", {{"name", scene.name}, {"file", scene.file}}}}
             .dump(2)
      << '\n';
    std::cerr << "needle_sim: numerical failure before the first step: " << e.what() << "\n"
              << "needle_sim: failure report in " << out_dir << "/summary.json\n";
    return kExitNumerical;
  }
  std::unique_ptr<RunRecorder> rec;
  std::unique_ptr<BagOutput> bag_out;
  try {
    rec = std::make_unique<RunRecorder>(*sim, out_dir, options);
    // Stamped as the recording when one drives the run, so both bags play side by side.
    if (!bag_run.out_bag.empty())
      bag_out = std::make_unique<BagOutput>(bag_run.out_bag, bag_run.out_ns, *sim, bag_run.given() ? session.origin : 0.0);
  } catch (const std::exception& e) {
    std::cerr << "needle_sim: " << e.what() << '\n';
    return kExitInput;
  }
  const long n = scene.numSteps();
  if (!quiet)
    std::cerr << "needle_sim: scene '" << scene.name << "': " << sim->numDofs() << " dofs, " << sim->numElements()
              << " elements, " << n << " steps\n";
  using clock = std::chrono::steady_clock;
  const auto t_start = clock::now();
  auto t_report = t_start;
  std::vector<double> sim_t, sim_force;  // the bag's needle's axial force on its holder, for the measured one
  bool assim_failed = false;
  for (long k = 0; k < n; ++k) {
    const auto t0 = clock::now();
    try {
      if (replay) replay->beforeStep(*sim);
      const StepStats& s = sim->step();
      const double ms = std::chrono::duration<double, std::milli>(clock::now() - t0).count();
      rec->recordStep(s, ms);
      if (replay) {  // the step's observables, as its timeseries.csv row
        sim_t.push_back(rec->observables().time);
        sim_force.push_back(rec->observables().needles[bag_needle].axial_force);
      }
      if (bag_out) bag_out->record(*sim, ms);
      // The measurement up to this step's time has arrived: the estimate at a checkpoint.
      if (assim && !assim_failed) {
        try {
          if (assim->advance(sim->time()) > 0 && !quiet) {
            const auto& k = assim->checkpoints().back();
            std::cerr << "needle_sim: assimilation at t=" << k.t << " s (" << k.samples << " samples):";
            for (size_t i = 0; i < k.values.size(); ++i)
              std::cerr << ' ' << assim->parameters()[i].key << '=' << k.values[i] << " +- " << k.stds[i];
            std::cerr << '\n';
          }
        } catch (const NumericalError& e) {  // the estimate's simulations, not the run's
          assim_failed = true;
          std::cerr << "needle_sim: assimilation stopped (its estimates so far are kept): " << e.what() << '\n';
        }
      }
    } catch (const NumericalError& e) {
      const double wall = std::chrono::duration<double>(clock::now() - t_start).count();
      rec->fail(wall, e.step(), e.what());
      if (bag_out) bag_out->close();  // the steps before the failure (a failed state is never written)
      std::cerr << "needle_sim: numerical failure: " << e.what() << "\n"
                << "needle_sim: failure report in " << rec->summaryPath() << '\n';
      return kExitNumerical;
    }
    if (!quiet && clock::now() - t_report > std::chrono::seconds(2)) {
      t_report = clock::now();
      std::cerr << "needle_sim: step " << sim->stepIndex() << "/" << n << "  t=" << sim->time() << " s\n";
    }
  }
  if (assim && !assim_failed) {
    try {
      assim->finish(sim->time());
    } catch (const NumericalError& e) {
      std::cerr << "needle_sim: assimilation stopped (its estimates so far are kept): " << e.what() << '\n';
    }
  }
  const double wall = std::chrono::duration<double>(clock::now() - t_start).count();
  rec->finish(wall);
  if (assim) writeAssimilation(*assim, assimilate, out_dir, observableNames(*sim).targets);
  if (bag_out) {
    bag_out->close();
    std::printf("needle_sim: %ld messages written to %s\n", bag_out->messages(), bag_run.out_bag.c_str());
  }
  if (replay) {
    const auto& g = replay->guard();
    std::printf("needle_sim: bag %s: %zu commands on %s, %ld followed, %lu rejected (", bag_run.bag.c_str(),
                session.commands.size(), bag_run.pose_topic.c_str(), replay->accepted(),
                static_cast<unsigned long>(g.rejected()));
    bool first = true;
    for (int r = 0; r < kGuardRules; ++r)
      if (g.count(static_cast<GuardRule>(r)) > 0) {
        std::printf("%s%s %lu", first ? "" : ", ", ruleName(static_cast<GuardRule>(r)),
                    static_cast<unsigned long>(g.count(static_cast<GuardRule>(r))));
        first = false;
      }
    std::printf("%s)\n", first ? "none" : "");
    if (!bag_run.wrench_topic.empty() && !session.force.t.empty() && !sim_t.empty()) {
      std::ofstream f(out_dir + "/measured_force.csv");
      f << "t,measured_axial_force,simulated_axial_force\n";
      f.precision(10);
      double se = 0;
      long m = 0;
      for (size_t i = 0; i < session.force.t.size(); ++i) {
        if (session.force.t[i] > sim_t.back()) break;
        if (!std::isfinite(session.force.force[i])) continue;  // a row of another sensor
        const double fs = interpolate(sim_t, sim_force, session.force.t[i]);
        f << session.force.t[i] << ',' << session.force.force[i] << ',' << fs << '\n';
        se += (fs - session.force.force[i]) * (fs - session.force.force[i]);
        ++m;
      }
      std::printf("needle_sim: measured force on %s: %ld samples, rms difference to the simulated %.4e N (%s/measured_force.csv)\n",
                  bag_run.wrench_topic.c_str(), m, m ? std::sqrt(se / m) : 0.0, out_dir.c_str());
    }
  }
  const auto p = rec->stepTimes().percentiles();
  std::printf("needle_sim: %ld steps in %.3f s (step median %.3f ms, p99.9 %.3f ms, max %.3f ms)\n", n, wall,
              p.median, p.p999, p.max);
  const Observables o = observe(*sim);
  const ObservableNames names = observableNames(*sim);
  for (size_t i = 0; i < o.probe_displacement.size(); ++i) {
    const Vec3& u = o.probe_displacement[i];
    std::printf("  probe %-6s u = (% .6e, % .6e, % .6e) m\n", names.probes[i].c_str(), u[0], u[1], u[2]);
  }
  for (size_t i = 0; i < o.needles.size(); ++i) {
    const NeedleObservation& n = o.needles[i];
    std::printf("  needle %-6s tip = (% .6e, % .6e, % .6e) m, axial force on the holder % .4e N (base frame: "
                "% .3e, % .3e, % .3e), %s\n",
                names.needles[i].c_str(), n.tip[0], n.tip[1], n.tip[2], n.axial_force, n.holder_force_base[0],
                n.holder_force_base[1], n.holder_force_base[2], toString(n.state));
  }
  std::printf("results: %s\n         %s\n", rec->summaryPath().c_str(), rec->timeseriesPath().c_str());
  if (options.vtu_every > 0)
    std::printf("ParaView: %s/tissue.pvd, %s/needles.pvd (every %d steps)\n", out_dir.c_str(), out_dir.c_str(),
                options.vtu_every);
  return 0;
}

// The scene's value keys as their modules declare them (scene/scene_keys.hpp): a table per
// section, or only the sections named; Markdown for doc/scene_format.md.
int keysCommand(const std::vector<std::string>& only, bool markdown) {
  for (const SceneSection& s : sceneSections()) {
    if (!only.empty() && std::find(only.begin(), only.end(), s.path) == only.end()) continue;
    if (markdown) {
      std::printf("%s", sceneKeysMarkdown(s).c_str());
      continue;
    }
    std::printf("%s (%s)\n", s.path.c_str(), s.header.c_str());
    for (const auto& d : s.keys)
      std::printf("  %-28s %-24s %-12s %s\n", d.key.c_str(), (d.type() + (d.unit.empty() ? "" : " [" + d.unit + "]")).c_str(),
                  d.required ? "required" : d.default_text.c_str(),
                  d.kind == ParameterKind::Real || d.kind == ParameterKind::Integer ? d.range.text().c_str() : "");
  }
  return 0;
}

}  // namespace

// roslaunch appends "__name:=..." and "__log:=..." to a node's arguments; they mean nothing
// to this tool, so they are dropped (as ros::removeROSArgs would) before parsing.
std::vector<std::string> withoutRosArgs(int argc, char** argv) {
  std::vector<std::string> args;
  for (int i = argc - 1; i >= 1; --i) {  // CLI11 takes the arguments in reverse order
    const std::string a = argv[i];
    if (a.rfind("__", 0) == 0 && a.find(":=") != std::string::npos) continue;
    args.push_back(a);
  }
  return args;
}

int main(int argc, char** argv) {
  if (argc > 1 && std::string(argv[1]) == "ensemble") {
    // The ensemble tool is Python on Dask (doc/ensemble.md): it gets the other arguments, and
    // this executable as the tool its tasks run (unless $NEEDLE_SIM_TOOL names another).
    const std::string script = ensembleScript(), self = executablePath();
    std::vector<char*> args{const_cast<char*>("/usr/bin/python3"), const_cast<char*>(script.c_str())};
    args.insert(args.end(), argv + 2, argv + argc);
    args.push_back(nullptr);
    if (!self.empty()) setenv("NEEDLE_SIM_TOOL", self.c_str(), 0);
    // The script imports the package needle_sim: the environment's (a sourced devel or
    // install space, `pip install -e .`) first, else this executable's (appended).
    if (const std::string py = pythonPackageRoot(); !py.empty()) {
      const char* path = std::getenv("PYTHONPATH");
      setenv("PYTHONPATH", (path && *path ? std::string(path) + ":" + py : py).c_str(), 1);
    }
    execv(args[0], args.data());
    std::cerr << "needle_sim: cannot run /usr/bin/python3 " << script << ": " << std::strerror(errno) << '\n';
    return 1;
  }
  needle_sim::limitOpenMpThreads(argv);
  flushDenormalsToZero();
  retainFreedHeap();
  CLI::App app{"needle_sim: real-time, error-controlled FE simulation of needle insertion (headless driver)", "needle_sim"};
  app.require_subcommand(1);
  int blas_threads = 1;
  app.add_option("--blas-threads", blas_threads,
                 "threads of the BLAS under CHOLMOD (1: predictable step times; 2 speeds up large "
                 "factorisations)")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  // Loading a scene (the brain shift) runs before any step. One thread by default: more pay
  // a few per cent on an idle machine and cost 2-4x when another process keeps a core busy
  // (OpenBLAS's threads spin; doc/method.md "Brain shift").
  int setup_threads = 1;
  app.add_option("--setup-threads", setup_threads,
                 "BLAS threads while a scene loads (the brain-shift pre-step and the first factor, before "
                 "any step; 0: every core, at most 8); the steps then run with --blas-threads")
      ->capture_default_str()
      ->check(CLI::Range(0, 64));

  std::string scene_path, out_dir;
  std::vector<std::string> sets;
  bool quiet = false;
  RunRecorder::Options rec_opts;
  app.footer("Scenes named without a folder are looked up in the package's config/scenes. Reference: doc/cli.md.\n"
             "needle_sim ensemble --help: many runs of a scene with sampled values, on Dask (doc/ensemble.md).");
  auto* run = app.add_subcommand("run", "run a scene headless: summary.json, timeseries.csv, optional VTU series");
  run->add_option("scene", scene_path, "scene file (YAML)")->required();
  run->add_option("--out,-o", out_dir, "output directory")->required();
  run->add_option("--set", sets, "override a scene value: key.path=value (repeatable)");
  run->add_flag("--quiet,-q", quiet, "no progress on stderr");
  run->add_flag("--centerline", rec_opts.centerline, "also write DIR/centerline.csv: every needle node at every step");
  run->add_option("--wrench-rate", rec_opts.wrench_rate,
                  "also write DIR/wrench.csv: every needle's force and moment on its holder at this rate [Hz], "
                  "between the steps extrapolated from the commanded base motion (as the node's ~wrench_rate)")
      ->check(CLI::Range(0.0, 1e6));
  run->add_flag("--error-estimate", rec_opts.error_estimate,
                "SPR error estimate of the tissue every step (eta_global, eta_max, eta_relative columns)");
  run->add_flag("--vtu", rec_opts.vtu, "also write DIR/tissue.vtu: the final mesh with displacement, von Mises stress, eta");
  run->add_flag("--target-error", rec_opts.target_error,
                "goal-oriented estimate of each target's displacement error: <name>_err_* columns, summary.json "
                "targets.<name>.error_estimate and error_bound");
  run->add_option("--target-error-every", rec_opts.target_error_every, "... every N steps (default 1)")
      ->check(CLI::PositiveNumber);
  BagRun bag_run;
  run->add_option("--bag", bag_run.bag, "drive the needle from the commanded base poses recorded in this bag (replaces the scene's motion and duration)");
  run->add_option("--pose-topic", bag_run.pose_topic, "... on this geometry_msgs/PoseStamped topic (e.g. needle_sim/needle/command_pose)");
  run->add_option("--wrench-topic", bag_run.wrench_topic, "... and compare with the measured geometry_msgs/WrenchStamped on this topic: DIR/measured_force.csv");
  run->add_option("--needle", bag_run.needle, "... for this needle (default: the first)");
  run->add_option("--tip-topic", bag_run.tip_topic,
                  "... with --assimilate: a tracked tip (geometry_msgs/PointStamped, tissue frame; --tip-noise)");
  run->add_option("--target-topic", bag_run.target_topic,
                  "... with --assimilate: a target's measured position (geometry_msgs/PointStamped, tissue frame; --target-noise)");
  run->add_option("--measured-target", bag_run.measured_target, "... the target --target-topic measures (default: the first)");
  run->add_option("--shape-topic", bag_run.shape_topic,
                  "... with --assimilate: the needle's measured shape (geometry_msgs/PoseArray, tissue frame, the last pose "
                  "at the tip; --shape-noise, --shape-spacing)");
  run->add_option("--shape-spacing", bag_run.shape_spacing, "... the arc length between the shape's poses [m]")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  run->add_option("--out-bag", bag_run.out_bag, "also write the outputs as a rosbag on the node's topics (status, wrenches, targets, paths)");
  run->add_option("--out-bag-ns", bag_run.out_ns, "... under this namespace (the node's name)")->capture_default_str();
  run->add_option("--vtu-every", rec_opts.vtu_every,
                  "a ParaView series every N steps: DIR/vtu/, DIR/tissue.pvd, DIR/needles.pvd (0: none)")
      ->check(CLI::Range(0.0, 1e6));
  AssimilateOptions assimilate;
  run->add_option("--assimilate", assimilate.keys,
                  "estimate these scene keys (comma-separated) online from the measured holder force (--data, or "
                  "--bag with --wrench-topic): DIR/assimilation.csv, DIR/innovation.csv, summary.json assimilation")
      ->delimiter(',');
  run->add_option("--data", assimilate.data,
                  "... the measurement: a CSV with t [s] and axial_force [N] (calibrate's) and/or a tracked tip tip_x, tip_y, tip_z [m] "
                  "and/or a target's measured position <target>_x, _y, _z [m]");
  run->add_option("--noise", assimilate.noise, "... the force's noise, a standard deviation [N] (default: from the residuals)")
      ->check(CLI::PositiveNumber);
  run->add_option("--tip-noise", assimilate.tip_noise,
                  "... the tip's noise, a standard deviation per coordinate [m] (needed with the force's to weigh both)")
      ->check(CLI::PositiveNumber);
  run->add_option("--target-noise", assimilate.target_noise,
                  "... a measured target's noise, a standard deviation per coordinate [m] (columns <target>_x, _y, _z)")
      ->check(CLI::PositiveNumber);
  run->add_option("--shape-noise", assimilate.shape_noise,
                  "... a measured shape's noise, a standard deviation per coordinate of each point [m] (--shape-topic)")
      ->check(CLI::PositiveNumber);
  run->add_option("--assimilate-every", assimilate.every, "... a checkpoint every S seconds of data (default: a tenth)")
      ->check(CLI::PositiveNumber);
  run->add_option("--start", assimilate.starts, "... a key's start: key=value (default: the scene's value)");
  run->add_option("--bounds", assimilate.bounds, "... a key's bounds: key=lower:upper (default: its declared range)");

  std::vector<std::string> key_sections;
  bool keys_markdown = false;
  auto* keys = app.add_subcommand("keys", "list the scene's value keys: type, unit, default, range (doc/scene_format.md)");
  keys->add_option("section", key_sections, "only these sections (time, solver, tissue, tissue.grid, needle, needle.bevel, "
                                            "interaction, adaptivity, brain_shift)");
  keys->add_flag("--markdown", keys_markdown, "as the Markdown tables of doc/scene_format.md");
  CheckOptions check_opts;
  auto* check = app.add_subcommand("check", "validate a scene and build its mesh, without running it");
  check->add_option("scene", check_opts.scene, "scene file (YAML)")->required();
  check->add_option("--set", check_opts.sets, "override a scene value: key.path=value (repeatable)");
  check->add_flag("--json", check_opts.json,
                  "print the scene as the loader resolved it (after extends and --set) as JSON: its tree, the "
                  "needles with their --set prefixes and planned final tips, the targets and probes");
  check->add_option("--aim", check_opts.aims,
                    "ENTRY_X ENTRY_Y ENTRY_Z TARGET_X TARGET_Y TARGET_Z [m]: the --set overrides that move the needles "
                    "rigidly, as one tool, so that the first one's planned final tip lands on the target and its axis "
                    "on entry -> target (repeatable; implies --json: its \"aims\")")
      ->type_size(6)
      ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
  check->add_option("--aim-needles", check_opts.aim_needles, "the needles --aim moves (default: all; the first in scene "
                                                             "order is the one aimed)")
      ->delimiter(',');
  check->add_option("--preflight", check_opts.preflight,
                    "S: time up to S seconds of the scene's own motion, paced at dt, and say whether it keeps real "
                    "time here (0: not; default 2 s, and 0 with --json or --aim)")
      ->check(CLI::Range(0.0, 600.0));

  BenchOptions bench_opts;
  auto* bench = app.add_subcommand("bench", "time the steps of a scene at several grids, split by phase");
  bench->add_option("--scene", bench_opts.scene, "scene to time")->capture_default_str();
  bench->add_option("--cells", bench_opts.cells, "grids to time, e.g. 8x4x4 16x8x8")->capture_default_str();
  bench->add_option("--steps", bench_opts.steps, "timed steps per grid (0: every step of the scene)")->capture_default_str();
  bench->add_option("--warmup", bench_opts.warmup, "untimed steps first")->capture_default_str();
  bench->add_option("--set", bench_opts.sets, "override a scene value (repeatable)");
  bench->add_flag("--compare-direct", bench_opts.compare_direct,
                  "also run with a fresh factorisation every step and report the probe difference");
  bench->add_option("--json", bench_opts.json_out, "also write the results as JSON to this file");
  bench->add_option("--target-error-every", bench_opts.target_error_every,
                    "adaptive scenes: time the goal-oriented target estimate every N steps as its own phase");
  bench->add_option("--target", bench_opts.target, "add a target at this planning position: x y z [m]")->expected(3);
  bench->add_flag("--pace", bench_opts.pace, "adaptive scenes: start step k at k dt (a real-time loop), not back to back");
  bench->add_option("--slowest", bench_opts.slowest, "adaptive scenes: also list the N slowest steps and their phases");

  PredictOptions pred;
  auto* predict = app.add_subcommand("predict", "predict a straight insertion on a copy of a running scene, timed");
  predict->add_option("scene", pred.scene, "scene file (YAML)")->required();
  predict->add_option("--set", pred.sets, "override a scene value (repeatable)");
  predict->add_option("--needle", pred.needle, "needle that follows the plan (default: the first)");
  predict->add_option("--at", pred.at, "run the scene live to this time first [s]")->capture_default_str();
  predict->add_option("--advance", pred.advance, "the plan: the base advances this far along its axis [m]")->capture_default_str();
  predict->add_option("--over", pred.over, "... over this long [s] (0: the whole duration)")->capture_default_str();
  predict->add_option("--duration", pred.duration, "simulated time of the prediction [s]")->capture_default_str();
  predict->add_option("--dt", pred.dt, "time step of the prediction [s] (0: the scene's)")->capture_default_str();
  predict->add_option("--sample-period", pred.sample_period, "spacing of the output samples [s]")->capture_default_str();
  predict->add_option("--target", pred.target, "add a target at this planning position: x y z [m]")->expected(3);
  predict->add_option("--repeat", pred.repeat, "predictions timed (median reported)")->capture_default_str();
  predict->add_flag("--compare", pred.compare, "also predict at the scene's dt and report the largest differences");
  predict->add_option("--csv", pred.csv, "write the last prediction's samples to this file");
  predict->add_option("--json", pred.json_out, "also write the results as JSON to this file");

  SteerOptions steer_opts;
  auto* steer = app.add_subcommand("steer", "plan a bevel-tip needle's roll-flip insertion to a target on the simulator's prediction, then run it");
  steer->add_option("scene", steer_opts.scene, "scene file (YAML), with a bevel-tipped needle")->required();
  steer->add_option("--set", steer_opts.sets, "override a scene value (repeatable)");
  steer->add_option("--target", steer_opts.target, "the target: x y z [m], tissue frame")->expected(3)->required();
  steer->add_option("--needle", steer_opts.needle, "needle to steer (default: the first)");
  steer->add_option("--speed", steer_opts.speed, "insertion speed [m/s]")->capture_default_str();
  steer->add_option("--roll-rate", steer_opts.roll_rate, "roll rate of the base for the turns [rad/s] (0: --max-angular-speed, at most pi)")->capture_default_str();
  steer->add_option("--max-speed", steer_opts.max_speed, "the live run's guard: base translation limit [m/s] (the node's ~max_speed)")->capture_default_str();
  steer->add_option("--max-angular-speed", steer_opts.max_angular_speed, "the live run's guard: base rotation limit [rad/s] (the node's ~max_angular_speed)")->capture_default_str();
  steer->add_option("--dt", steer_opts.dt, "time step of the predictions [s] (0: the scene's)")->capture_default_str();
  steer->add_option("--tolerance", steer_opts.tolerance, "done when the predicted tip is this close [m]")->capture_default_str();
  steer->add_option("--max-predictions", steer_opts.max_predictions, "predictions at most")->capture_default_str();
  steer->add_flag("!--no-live", steer_opts.live, "do not run the plan live afterwards");
  steer->add_option("--json", steer_opts.json_out, "also write the plan and the results as JSON to this file");

  SoakOptions soak_opts;
  auto* soak = app.add_subcommand("soak", "long back-and-forth insertion: memory, step time, energy per window");
  soak->add_option("scene", soak_opts.scene, "scene file (YAML)")->required();
  soak->add_option("--set", soak_opts.sets, "override a scene value (repeatable)");
  soak->add_option("--steps", soak_opts.steps, "steps to run")->capture_default_str();
  soak->add_option("--window", soak_opts.window, "steps per reported window (0: one cycle)")->capture_default_str();
  soak->add_option("--depth", soak_opts.depth, "insertion depth per cycle [m]")->capture_default_str();
  soak->add_option("--speed", soak_opts.speed, "insertion and withdrawal speed [m/s]")->capture_default_str();
  soak->add_option("--hold", soak_opts.hold, "hold at depth and at the start [s]")->capture_default_str();
  soak->add_option("--max-growth-mb", soak_opts.max_growth_mb,
                   "exit 1 if the heap in use grows more than this from the second window to the last full one (0: report only)")
      ->capture_default_str();
  soak->add_option("--csv", soak_opts.csv, "per-window rows");
  soak->add_option("--json", soak_opts.json_out, "summary as JSON");

  CalibrateOptions cal;
  auto* calibrate = app.add_subcommand("calibrate", "fit scene keys so that the simulated holder force matches a recorded one");
  calibrate->add_option("scene", cal.scene, "scene file (YAML); its needle motion is the recorded robot motion")->required();
  calibrate->add_option("--data", cal.data,
                        "recorded force: CSV with columns t [s], axial_force [N, the needle's force on its holder along it: < 0 when the tissue resists], or a bag (with the topics)")
      ->required();
  calibrate->add_option("--pose-topic", cal.pose_topic, "bag: the commanded base poses (geometry_msgs/PoseStamped): the motion");
  calibrate->add_option("--wrench-topic", cal.wrench_topic, "bag: the measured wrench (geometry_msgs/WrenchStamped, <needle>_base frame)");
  calibrate->add_option("--fit", cal.fit, "scene keys to fit, comma-separated (e.g. interaction.cutting_force,interaction.grip_pressure)")
      ->required();
  calibrate->add_option("--start", cal.starts, "start value of a fitted key: key=value (default: the scene's)");
  calibrate->add_option("--bounds", cal.bounds, "bounds of a fitted key: key=lower:upper (default: from the key's declared range)");
  calibrate->add_option("--set", cal.sets, "override a fixed scene value (repeatable)");
  calibrate->add_option("--needle", cal.needle, "needle whose holder force is fitted (default: the first)");
  calibrate->add_option("--max-evaluations", cal.max_evaluations, "simulations the optimiser may run")
      ->capture_default_str()
      ->check(CLI::Range(1, 100000));
  calibrate->add_option("--xtol-rel", cal.xtol_rel, "stop when the parameters change by less than this, relative")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  calibrate->add_option("--out,-o", cal.out, "output directory: calibration.json, fit.csv, fit.png")->required();
  calibrate->add_flag("!--no-plot", cal.plot, "do not write fit.png");
  calibrate->add_flag("--quiet,-q", cal.quiet, "no progress on stderr");

  try {
    auto args = withoutRosArgs(argc, argv);
    app.parse(args);
    setBlasThreads(blas_threads);
    Simulation::setSetupThreads(threadsOrEveryCore(setup_threads));
    scene_path = resolveScene(scene_path);
    if (*check) check_opts.scene = resolveScene(check_opts.scene);
    bench_opts.scene = resolveScene(bench_opts.scene);
    pred.scene = resolveScene(pred.scene);
    steer_opts.scene = resolveScene(steer_opts.scene);
    soak_opts.scene = resolveScene(soak_opts.scene);
    if (*calibrate) cal.scene = resolveScene(cal.scene);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitInput;
  }
  try {
    if (*run) {
      assimilate.target_error = rec_opts.target_error;  // --target-error: the bound joins the targets' covariance
      return runCommand(scene_path, out_dir, sets, quiet, rec_opts, bag_run, assimilate);
    }
    if (*check) return checkCommand(check_opts);
    if (*keys) return keysCommand(key_sections, keys_markdown);
    if (*bench) return benchCommand(bench_opts);
    if (*predict) return predictCommand(pred);
    if (*steer) return steerCommand(steer_opts);
    if (*soak) return soakCommand(soak_opts);
    if (*calibrate) return calibrateCommand(cal);
  } catch (const InputError& e) {
    std::cerr << "needle_sim: invalid input: " << e.what() << '\n';
    return kExitInput;
  } catch (const NumericalError& e) {
    std::cerr << "needle_sim: numerical failure: " << e.what() << '\n';
    return kExitNumerical;
  } catch (const std::exception& e) {
    std::cerr << "needle_sim: error: " << e.what() << '\n';
    return 1;
  }
  return 0;
}
