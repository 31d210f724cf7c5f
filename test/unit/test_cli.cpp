// The needle_sim command-line tool as a user runs it: exit status 2 with a message naming
// the file and key for every bad scene, 0 with complete results for a good run, 3 with a
// failure report (and no result that looks like a success) on a numerical failure.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <map>
#include <set>
#include <sstream>

using nlohmann::json;
namespace fs = std::filesystem;

namespace {
const std::string kSrc = NEEDLE_SIM_SOURCE_DIR;
const std::string kTool = NEEDLE_SIM_TOOL;

struct Result {
  int status;
  std::string err;
};

Result runTool(const std::string& args) {
  const fs::path errfile = fs::temp_directory_path() / ("needle_sim_cli_" + std::to_string(::getpid()) + ".err");
  const std::string cmd = "'" + kTool + "' " + args + " >/dev/null 2>'" + errfile.string() + "'";
  const int raw = std::system(cmd.c_str());
  std::ifstream in(errfile);
  std::stringstream ss;
  ss << in.rdbuf();
  fs::remove(errfile);
  return {WIFEXITED(raw) ? WEXITSTATUS(raw) : -1, ss.str()};
}

// A command's standard output.
std::string capture(const std::string& cmd) {
  std::string out;
  if (FILE* p = ::popen(cmd.c_str(), "r")) {
    char buf[4096];
    for (size_t k; (k = std::fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, k);
    ::pclose(p);
  }
  return out;
}

// The message count of a topic in `rosbag info --yaml` output (-1: not in the bag).
long topicCount(const std::string& info, const std::string& topic) {
  const size_t at = info.find("topic: " + topic + "\n");
  if (at == std::string::npos) return -1;
  const size_t m = info.find("messages:", at);
  return m == std::string::npos ? -1 : std::stol(info.substr(m + 9));
}

fs::path freshDir(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("needle_sim_cli_" + std::to_string(::getpid())) / name;
  fs::remove_all(d);
  return d;
}

// First line of a CSV file (empty if it cannot be read).
std::string csvHeader(const fs::path& file) {
  std::ifstream in(file);
  std::string header;
  std::getline(in, header);
  return header;
}

std::string firstLine(const fs::path& p) {
  std::ifstream in(p);
  std::string line;
  std::getline(in, line);
  return line;
}
}  // namespace

TEST(Cli, BadScenesExitWithStatus2AndNameFileAndKey) {
  for (const auto& e : fs::directory_iterator(kSrc + "/test/data/bad_scenes")) {
    SCOPED_TRACE(e.path().string());
    const fs::path out = freshDir("bad");
    const Result r = runTool("run '" + e.path().string() + "' --out '" + out.string() + "'");
    EXPECT_EQ(r.status, 2) << r.err;
    EXPECT_NE(r.err.find(e.path().string()), std::string::npos) << r.err;
    const std::string key = firstLine(e.path()).substr(std::string("# expect-key: ").size());
    if (!key.empty()) {
      EXPECT_NE(r.err.find("'" + key), std::string::npos) << r.err;
    }
    EXPECT_FALSE(fs::exists(out / "summary.json"));
  }
}

TEST(Cli, RunWritesSummaryAndTimeseries) {
  const fs::path out = freshDir("ok");
  const Result r = runTool("run '" + kSrc + "/config/scenes/phantom_8x4x4.yaml' --out '" + out.string() +
                           "' --set time.duration=0.02 --quiet");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream in(out / "summary.json");
  const json j = json::parse(in);
  EXPECT_EQ(j["status"], "ok");
  EXPECT_EQ(j["scene"]["name"], "phantom_8x4x4");
  EXPECT_EQ(j["dofs"], 675);
  EXPECT_EQ(j["elements"], 128);
  EXPECT_EQ(j["steps"], 20);
  for (const char* k : {"median", "p95", "max"}) EXPECT_GT(j["step_ms"][k].get<double>(), 0.0);
  EXPECT_EQ(j["probes"].size(), 12u);
  // Gravity pulls every probe down.
  EXPECT_LT(j["probes"]["p1"]["displacement"][2].get<double>(), 0.0);
  // Header plus one row per step, probe columns present.
  std::ifstream csv(out / "timeseries.csv");
  std::string header, line;
  std::getline(csv, header);
  EXPECT_NE(header.find("step,t,dofs,step_ms"), std::string::npos);
  EXPECT_NE(header.find("p1E_ux,p1E_uy,p1E_uz"), std::string::npos);
  // The names in scene order (summary.json's objects sort their keys): the columns' order.
  ASSERT_EQ(j["names"]["probes"].size(), 12u);
  EXPECT_TRUE(j["names"]["needles"].empty());
  EXPECT_TRUE(j["names"]["targets"].empty());
  size_t at = 0;
  for (const auto& p : j["names"]["probes"]) {
    const size_t next = header.find("," + p.get<std::string>() + "_ux,");
    EXPECT_NE(next, std::string::npos) << p;
    EXPECT_GT(next, at) << p << " is out of scene order";
    at = next;
    EXPECT_TRUE(j["probes"].contains(p.get<std::string>())) << p;
  }
  int rows = 0;
  while (std::getline(csv, line)) ++rows;
  EXPECT_EQ(rows, 20);
  EXPECT_FALSE(fs::exists(out / "timeseries.partial.csv"));
}

TEST(Cli, NumericalFailureExitsWith3AndLeavesNoSuccessLookalike) {
  const fs::path out = freshDir("fail");
  // A large load and a single Newton iteration: the static solve cannot converge.
  const Result r = runTool("run '" + kSrc + "/config/scenes/cantilever_hex8.yaml' --out '" + out.string() +
                           "' --set solver.static.max_iterations=1 --set tissue.tractions.0.traction=[0,100,0]");
  EXPECT_EQ(r.status, 3) << r.err;
  EXPECT_NE(r.err.find("step 1"), std::string::npos) << r.err;
  std::ifstream in(out / "summary.json");
  const json j = json::parse(in);
  EXPECT_EQ(j["status"], "numerical_failure");
  EXPECT_EQ(j["failed_step"], 1);
  EXPECT_FALSE(fs::exists(out / "timeseries.csv"));
}

TEST(Cli, UsageErrorsExitWith2) {
  EXPECT_EQ(runTool("").status, 2);
  EXPECT_EQ(runTool("run").status, 2);
  EXPECT_EQ(runTool("frobnicate").status, 2);
  const fs::path out = freshDir("usage");
  EXPECT_EQ(runTool("run /nonexistent/scene.yaml --out '" + out.string() + "'").status, 2);
  EXPECT_EQ(runTool("run '" + kSrc + "/config/scenes/phantom_8x4x4.yaml' --out '" + out.string() + "' --set nonsense").status, 2);
  EXPECT_EQ(runTool("check '" + kSrc + "/config/scenes/phantom_8x4x4.yaml'").status, 0);
  // The pre-flight (#40): plain check says whether the scene keeps real time here; --json
  // carries it when asked; a budget out of range is refused. The 32x16x16 reference cannot
  // keep its 1 ms step on any machine this runs on (tens of ms a step).
  const std::string tool = "'" + kTool + "' check ";
  const std::string pf = capture(tool + "phantom_insertion_32x16x16.yaml --preflight 0.3");
  EXPECT_NE(pf.find("pre-flight: "), std::string::npos) << pf;
  EXPECT_NE(pf.find("WILL NOT keep real time here, margin 0."), std::string::npos) << pf;
  const json p = json::parse(capture(tool + "phantom_insertion_8x4x4.yaml --json --set time.dt=0.05 --preflight 0.5"))
                     .at("preflight");
  EXPECT_TRUE(p["keeps_real_time"].get<bool>()) << p.dump();
  EXPECT_GT(p["margin"].get<double>(), 1.0);
  EXPECT_GE(p["steps"].get<long>(), 5);
  EXPECT_FALSE(json::parse(capture(tool + "phantom_insertion_8x4x4.yaml --json")).contains("preflight"));
  EXPECT_EQ(runTool("check phantom_insertion_8x4x4.yaml --preflight -1").status, 2);
  // A scene by its bare name, as the node and the docs' commands take it (#40 item 5).
  EXPECT_EQ(runTool("check phantom_insertion_8x4x4 --preflight 0").status, 0);
  // The target estimate is timed on adaptive scenes only: asked of another, a clear error.
  const auto b = runTool("bench --scene '" + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml' --target 0.022 0.01 0.01 "
                         "--target-error-every 20");
  EXPECT_EQ(b.status, 2) << b.err;
  EXPECT_NE(b.err.find("--target-error-every"), std::string::npos) << b.err;
}

TEST(Cli, PredictReportsAndRefusesBadPlans) {
  const std::string scene = "'" + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml'";
  const fs::path out = freshDir("predict");
  fs::create_directories(out);
  const Result ok = runTool("predict " + scene + " --duration 0.5 --advance 0.005 --dt 0.01 --target 0.01 0.01 0.01 " +
                            "--repeat 1 --json '" + (out / "p.json").string() + "' --csv '" + (out / "p.csv").string() + "'");
  ASSERT_EQ(ok.status, 0) << ok.err;
  std::ifstream jf(out / "p.json");
  std::stringstream js;
  js << jf.rdbuf();
  EXPECT_NE(js.str().find("\"steps\": 50"), std::string::npos) << js.str();
  std::ifstream cf(out / "p.csv");
  std::string header, line;
  std::getline(cf, header);
  EXPECT_NE(header.find("target_tip_distance"), std::string::npos) << header;
  int rows = 0;
  while (std::getline(cf, line)) ++rows;
  EXPECT_EQ(rows, 6);  // now and every 0.1 s
  for (const std::string bad : {"--at -1", "--dt -0.01", "--duration 0", "--target 1 1 1", "--needle nope", "--repeat 0"}) {
    const Result r = runTool("predict " + scene + " " + bad);
    EXPECT_EQ(r.status, 2) << bad << ": " << r.err;
    EXPECT_NE(r.err.find("invalid input"), std::string::npos) << bad << ": " << r.err;
  }
}

TEST(Cli, NeedleRunWritesTipBaseReactionAndCenterline) {
  const fs::path out = freshDir("needle");
  const Result r = runTool("run '" + kSrc + "/config/scenes/needle_free_motion.yaml' --out '" + out.string() +
                           "' --set time.duration=0.05 --quiet --centerline");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream in(out / "summary.json");
  const json j = json::parse(in);
  EXPECT_EQ(j["dofs"], 126);
  const auto& n = j["needles"]["needle"];
  EXPECT_EQ(n["elements"], 20);
  EXPECT_EQ(n["centerline"].size(), 21u);
  EXPECT_NEAR(n["direction"][0].get<double>(), 1.0, 1e-6);
  // The needle's force on its holder: its weight pulls the holder down; hardly any along it.
  EXPECT_LT(n["holder_force"][2].get<double>(), 0.0);
  EXPECT_LT(std::abs(n["axial_force"].get<double>()), 0.01 * std::abs(n["holder_force"][2].get<double>()));
  EXPECT_EQ(j["names"]["needles"], json::array({"needle"}));
  const std::string header = csvHeader(out / "timeseries.csv");
  for (const char* col : {"needle_tip_x", "needle_dir_z", "needle_holder_fx", "needle_holder_mz", "needle_axial_force"})
    EXPECT_NE(header.find(col), std::string::npos) << col;
  EXPECT_EQ(header.find("base_f"), std::string::npos);
  std::ifstream cl(out / "centerline.csv");
  std::string line;
  int rows = -1;
  while (std::getline(cl, line)) ++rows;
  EXPECT_EQ(rows, 50 * 21);
}

// The plot script draws PNG files from the runs' time series.
TEST(Cli, PlotScriptWritesPngFiles) {
  std::vector<fs::path> runs;
  for (const char* cells : {"[8,4,4]", "[16,8,8]"}) {
    const fs::path out = freshDir(std::string("plot") + cells[1]);
    const Result r = runTool("run '" + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml' --out '" + out.string() +
                             "' --quiet --set time.duration=0.4 --set tissue.grid.cells=" + cells);
    ASSERT_EQ(r.status, 0) << r.err;
    runs.push_back(out);
  }
  const fs::path png = freshDir("plots");
  const std::string cmd = "/usr/bin/python3 '" + kSrc + "/scripts/plot_probes.py' '" + runs[0].string() + "' '" +
                          runs[1].string() + "' --out '" + png.string() + "' > /dev/null";
  ASSERT_EQ(std::system(cmd.c_str()), 0);
  for (const char* f : {"probe_p1.png", "probe_p1E.png", "probes_along_path.png", "probes_radial.png"}) {
    std::ifstream in(png / f, std::ios::binary);
    char magic[8] = {};
    in.read(magic, 8);
    EXPECT_EQ(std::string(magic + 1, 3), "PNG") << f;
  }
  // A directory without results is a clear error, not a crash.
  const std::string bad = "/usr/bin/python3 '" + kSrc + "/scripts/plot_probes.py' /nonexistent --out '" +
                          png.string() + "' 2>/dev/null";
  const int raw = std::system(bad.c_str());
  EXPECT_EQ(WEXITSTATUS(raw), 1);
}

// The gel steering demo (config/scenes/gel_bevel_steering.yaml): 24 mm with the bevel
// pointing to +y, half a turn, 24 mm more. The cut path bends to +y, then back: an S whose
// highest point is at the roll; it stays in the x-y plane. The plot script draws it.
TEST(Cli, GelSteeringSceneCutsAnSAndPlotsIt) {
  const fs::path out = freshDir("gel");
  const Result r = runTool("run '" + kSrc + "/config/scenes/gel_bevel_steering.yaml' --out '" + out.string() + "' --quiet");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream in(out / "summary.json");
  const json path = json::parse(in)["needles"]["needle"]["cut_path"];
  ASSERT_GT(path.size(), 100u);
  double y_max = -1, x_at_max = 0, z_dev = 0;
  for (const auto& p : path) {
    if (p[1].get<double>() > y_max) y_max = p[1].get<double>(), x_at_max = p[0].get<double>();
    z_dev = std::max(z_dev, std::abs(p[2].get<double>() - 0.015));
  }
  EXPECT_GT(y_max - 0.015, 3e-3);                     // bent by over 3 mm towards +y (4.1 mm)
  EXPECT_NEAR(x_at_max, 0.024, 2e-3);                  // turned back at the roll
  // and back towards the axis after it: 0.20 mm on the shipped adaptive mesh and on a uniform
  // 2 mm grid (0.51 mm on the uniform 3 mm grid: doc/benchmarks.md "Bevel tip")
  EXPECT_LT(path.back()[1].get<double>(), y_max - 1e-4);
  EXPECT_LT(z_dev, 1e-4);                              // in the x-y plane (47 um)
  const std::string cmd = "/usr/bin/python3 '" + kSrc + "/scripts/plot_tip_path.py' '" + out.string() + "' > /dev/null";
  ASSERT_EQ(std::system(cmd.c_str()), 0);
  std::ifstream png(out / "tip_path.png", std::ios::binary);
  char magic[8] = {};
  png.read(magic, 8);
  EXPECT_EQ(std::string(magic + 1, 3), "PNG");
  // A run without a cut path is a clear error.
  const std::string bad = "/usr/bin/python3 '" + kSrc + "/scripts/plot_tip_path.py' /nonexistent 2>/dev/null";
  EXPECT_EQ(WEXITSTATUS(std::system(bad.c_str())), 2);
}

// `steer` refuses what it cannot plan with exit status 2 and the key, and plans a bevel
// phantom's S to a target below the axis (exit 0, the live tip where it was predicted).
TEST(Cli, SteerPlansABevelAndRefusesASymmetricTip) {
  const std::string scene = "'" + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml'";
  Result r = runTool("steer " + scene + " --target 0.018 0.0099 0.01");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.err.find("steer.needle"), std::string::npos) << r.err;
  r = runTool("steer " + scene + " --set needle.bevel.angle=0.5 --target 0.05 0.01 0.01");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.err.find("steer.target"), std::string::npos) << r.err;
#ifdef NEEDLE_SIM_SANITIZED
  return;  // two plans of 80 s each under the sanitizers: test_prediction's Steering runs the planner there
#endif
  const fs::path out = freshDir("steer");
  fs::create_directories(out);
  r = runTool("steer " + scene + " --set needle.bevel.angle=0.5235987755982988 --set interaction.shaft_spacing=0.0005"
              " --target 0.018 0.0099 0.01 --json '" + (out / "steer.json").string() + "'");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream in(out / "steer.json");
  const json j = json::parse(in);
  EXPECT_TRUE(j["reached"].get<bool>());
  EXPECT_FALSE(j["flip_depth"].is_null());
  EXPECT_LT(j["live_vs_predicted"].get<double>(), 1e-9);
  EXPECT_GE(j["waypoints"].size(), 4u);
  // The live run goes through the command pipeline: a roll faster than the guard's limit is
  // planned, but not run (the node would refuse it too).
  r = runTool("steer " + scene + " --set needle.bevel.angle=0.5235987755982988 --set interaction.shaft_spacing=0.0005"
              " --target 0.018 0.0099 0.01 --roll-rate 3 --max-angular-speed 1 --max-predictions 1 --json '" +
              (out / "refused.json").string() + "'");
  EXPECT_EQ(r.status, 1) << r.err;
  std::ifstream in2(out / "refused.json");
  const json k = json::parse(in2);
  ASSERT_TRUE(k.contains("live_refused"));
  EXPECT_NE(k["live_refused"].get<std::string>().find("angular_speed"), std::string::npos) << k["live_refused"];
  EXPECT_FALSE(k.contains("live_tip"));
}

// Error outputs on request: eta columns every step and the final mesh as a VTU file that
// parses as XML with one eta and one von Mises value per element.
TEST(Cli, ErrorEstimateAndVtuOnRequest) {
  const fs::path out = freshDir("vtu");
  const Result r = runTool("run '" + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml' --out '" + out.string() +
                           "' --quiet --error-estimate --vtu --set time.duration=0.5");
  ASSERT_EQ(r.status, 0) << r.err;
  EXPECT_NE(csvHeader(out / "timeseries.csv").find("eta_global,eta_max,eta_relative"), std::string::npos);
  const std::string check =
      "/usr/bin/python3 -c \"import sys, xml.etree.ElementTree as E; t = E.parse(sys.argv[1]); "
      "p = t.find('.//Piece'); assert p.get('NumberOfCells') == '128'; "
      "a = {d.get('Name'): d.text.split() for d in t.iter('DataArray')}; "
      "assert len(a['eta']) == 128 and len(a['von_mises']) == 128 and len(a['connectivity']) == 8 * 128; "
      "assert all(float(v) >= 0 for v in a['eta'])\" '" +
      (out / "tissue.vtu").string() + "'";
  EXPECT_EQ(std::system(check.c_str()), 0);
  // Without the flags, no estimate is computed and no columns appear.
  const fs::path plain = freshDir("novtu");
  ASSERT_EQ(runTool("run '" + kSrc + "/config/scenes/phantom_8x4x4.yaml' --out '" + plain.string() +
                    "' --quiet --set time.duration=0.01")
                .status,
            0);
  EXPECT_EQ(csvHeader(plain / "timeseries.csv").find("eta_"), std::string::npos);
  EXPECT_FALSE(fs::exists(plain / "tissue.vtu"));
}

// An adaptive run: DOFs, elements per level, estimate and costs per step; the summary's
// adaptivity section; the VTU's levels and element count agree with the final mesh.
TEST(Cli, AdaptiveRunOutputs) {
  const fs::path out = freshDir("adaptive");
  const Result r = runTool("run '" + kSrc + "/config/scenes/phantom_insertion_adaptive.yaml' --out '" + out.string() +
                           "' --quiet --vtu --set time.duration=1.0");
  ASSERT_EQ(r.status, 0) << r.err;
  const std::string header = csvHeader(out / "timeseries.csv");
  for (const char* col : {"eta_global", "tissue_elements", "elements_L0", "elements_L1", "elements_L2", "refined",
                          "coarsened", "estimate_ms", "mark_refine_ms", "rebuild_ms"})
    EXPECT_NE(header.find(col), std::string::npos) << col;
  EXPECT_EQ(header.find("elements_L3"), std::string::npos);
  const std::string check =
      "/usr/bin/python3 -c \"import sys, json, csv, xml.etree.ElementTree as E; d = sys.argv[1]; "
      "s = json.load(open(d + '/summary.json'))['adaptivity']; "
      "rows = list(csv.DictReader(open(d + '/timeseries.csv'))); last = rows[-1]; "
      "n = sum(s['elements_per_level']); assert n == int(last['tissue_elements']) and n > 128, n; "
      "assert s['tissue_dofs_final'] == int(last['dofs']) - 6 * 17, (s, last['dofs']); "
      "assert s['mesh_changes'] > 0 and s['cells_refined_total'] > 0; "
      "assert len(set(r['dofs'] for r in rows)) > 1; "
      "t = E.parse(d + '/tissue.vtu'); p = t.find('.//Piece'); assert int(p.get('NumberOfCells')) == n; "
      "a = {x.get('Name'): x.text.split() for x in t.iter('DataArray')}; "
      "lv = [int(v) for v in a['level']]; assert max(lv) == 2 and lv.count(2) == s['elements_per_level'][2]\" '" +
      out.string() + "'";
  EXPECT_EQ(std::system(check.c_str()), 0);
}

// calibrate's bad inputs: exit status 2 naming the problem, before any fitting.
TEST(Cli, CalibrateRejectsBadInputsWithStatus2) {
  const fs::path d = freshDir("calibrate");
  fs::create_directories(d);
  auto file = [&](const std::string& name, const std::string& text) {
    std::ofstream(d / name) << text;
    return (d / name).string();
  };
  const std::string good = file("good.csv", "t,axial_force\n0,0\n0.5,0.01\n1.0,0.02\n");
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml --set time.duration=1.0";
  const std::string out = " --out '" + (d / "out").string() + "' --no-plot --quiet";
  struct Case {
    std::string args, expect;
  };
  const std::vector<Case> cases = {
      {"--data '" + file("nocol.csv", "t,force\n0,1\n1,2\n") + "' --fit interaction.cutting_force", "axial_force"},
      {"--data '" + file("back.csv", "t,axial_force\n0,1\n1,2\n0.5,3\n") + "' --fit interaction.cutting_force", "increase"},
      {"--data '" + file("nan.csv", "t,axial_force\n0,1\n1,nan\n") + "' --fit interaction.cutting_force", "finite"},
      {"--data '" + good + "' --fit solver.linear.method", "not a number"},
      {"--data '" + good + "' --fit interaction.no_such_key --start interaction.no_such_key=1", "no_such_key"},
      {"--data '" + good + "' --fit needle.elements", "real-valued"},
      {"--data '" + good + "' --fit interaction.cutting_force --start interaction.friction=1", "not among the keys to fit"},
      {"--data '" + good + "' --fit interaction.cutting_force --bounds interaction.cutting_force=0.5:0.6", "outside"},
      {"--data '" + file("rec.bag", "") + "' --fit interaction.cutting_force", "needs --pose-topic"},
      {"--data '" + file("rec2.bag", "") + "' --fit interaction.cutting_force --pose-topic a --wrench-topic b", "cannot read the bag"},
      {"--data '" + good + "' --fit interaction.cutting_force --pose-topic a", "topics are for a bag"},
      {"--data '" + (d / "missing.csv").string() + "' --fit interaction.cutting_force", "cannot read"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.args);
    const Result r = runTool("calibrate " + scene + " " + c.args + out);
    EXPECT_EQ(r.status, 2) << r.err;
    EXPECT_NE(r.err.find(c.expect), std::string::npos) << r.err;
  }
  EXPECT_FALSE(fs::exists(d / "out" / "calibration.json"));
}

namespace {
// Columns of a CSV file by name.
std::map<std::string, std::vector<std::string>> readColumns(const fs::path& file) {
  std::ifstream in(file);
  std::string line;
  std::getline(in, line);
  std::vector<std::string> names;
  std::stringstream hs(line);
  for (std::string c; std::getline(hs, c, ',');) names.push_back(c);
  std::map<std::string, std::vector<std::string>> cols;
  while (std::getline(in, line)) {
    std::stringstream ls(line);
    size_t i = 0;
    for (std::string c; std::getline(ls, c, ',') && i < names.size(); ++i) cols[names[i]].push_back(c);
  }
  return cols;
}
}  // namespace

// The bag record.launch recorded (the scripted phantom insertion) replayed headless drives
// the needle through the command guard as the node does: the values the node's replay
// rostest (check_replay.py) expects during the hold, within its 5 % tolerances, and the tip's
// path; then the bad inputs of --bag.
TEST(Cli, RunFromABagMatchesTheNodesReplay) {
  const fs::path out = freshDir("bag");
  const std::string bag = kSrc + "/test/data/bags/phantom_insertion_commands.bag";
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml";
  const fs::path sim_bag = out / "simulated.bag";
  const Result r = runTool("run " + scene + " --quiet --out '" + out.string() + "' --bag '" + bag +
                           "' --pose-topic needle/command_pose --out-bag '" + sim_bag.string() + "'");
  ASSERT_EQ(r.status, 0) << r.err;
  auto cols = readColumns(out / "timeseries.csv");
  ASSERT_FALSE(cols["t"].empty());
  double p1 = 0, axial = 0, tip_max = -1;
  int n = 0;
  std::set<std::string> points;
  for (size_t i = 0; i < cols["t"].size(); ++i) {
    const double t = std::stod(cols["t"][i]);
    tip_max = std::max(tip_max, std::stod(cols["needle_tip_x"][i]));
    if (t < 2.35 || t > 2.45) continue;
    p1 += std::stod(cols["p1_ux"][i]);
    axial += std::stod(cols["needle_axial_force"][i]);
    points.insert(cols["constraint_points"][i]);
    ++n;
  }
  ASSERT_GT(n, 50);
  EXPECT_NEAR(p1 / n, 9.147e-8, 0.05 * 9.147e-8);
  EXPECT_NEAR(axial / n, -0.01950, 0.05 * 0.01950);  // the tissue holds the needle back
  EXPECT_EQ(points, std::set<std::string>{"20"});
  EXPECT_NEAR(tip_max, 0.019996, 5e-5);
  EXPECT_EQ(cols["needle_state"].back(), "out");
  std::ifstream in(out / "summary.json");
  EXPECT_EQ(json::parse(in)["status"], "ok");

  // --out-bag: what rosbag info reads (one status and one wrench per step, paths at 30 Hz of
  // simulated time), stamped from the recording's start, and the same holder force as the CSV.
  const std::string info = capture("/usr/bin/python3 /usr/bin/rosbag info --yaml '" + sim_bag.string() + "'");
  const long steps = static_cast<long>(cols["t"].size());
  EXPECT_EQ(topicCount(info, "/needle_sim/status"), steps) << info;
  EXPECT_EQ(topicCount(info, "/needle_sim/needle/wrench"), steps) << info;
  const double duration = std::stod(cols["t"].back());
  EXPECT_NEAR(topicCount(info, "/needle_sim/needle/path"), duration * 30, 2) << info;
  EXPECT_EQ(topicCount(info, "/needle_sim/target/state"), -1) << "the phantom has no targets";
  const std::string hold = capture(
      "/usr/bin/python3 -c \"import rosbag; b = rosbag.Bag('" + sim_bag.string() + "'); r = rosbag.Bag('" + bag +
      "'); t0 = r.get_start_time(); f = [m.wrench.force.x for _, m, t in b.read_messages(['/needle_sim/needle/wrench']) "
      "if 2.35 <= m.header.stamp.to_sec() - t0 <= 2.45]; print(len(f), sum(f) / len(f))\"");
  long held = 0;
  double wrench = 0;
  std::istringstream(hold) >> held >> wrench;
  EXPECT_GT(held, 50) << hold;
  EXPECT_NEAR(wrench, axial / n, 1e-9 * std::abs(axial / n)) << hold;  // the wrench's x is the axial force

  struct Case {
    std::string args, expect;
  };
  for (const Case& c : std::vector<Case>{
           {"--bag '" + bag + "' --pose-topic needle/no_such_topic", "no message"},
           {"--bag '" + bag + "'", "--pose-topic"},
           {"--bag '" + bag + "' --pose-topic needle/command_pose --wrench-topic needle/command_pose", "not geometry_msgs/WrenchStamped"},
           {"--bag '" + (out / "missing.bag").string() + "' --pose-topic needle/command_pose", "cannot read the bag"},
           {"--bag '" + bag + "' --pose-topic needle/command_pose --needle nobody", "no needle named"}}) {
    SCOPED_TRACE(c.args);
    const Result b = runTool("run " + scene + " --quiet --out '" + freshDir("badbag").string() + "' " + c.args);
    EXPECT_EQ(b.status, 2) << b.err;
    EXPECT_NE(b.err.find(c.expect), std::string::npos) << b.err;
  }
}

// One axial force with one sign in every report (observables.hpp): the needle's force on its
// holder along the needle, negative while the tissue resists the insertion. The phantom
// replayed from the shipped bag cuts at about -20 mN; timeseries.csv's needle_axial_force,
// summary.json's axial_force, the x of the wrench --out-bag writes (the node's conversion),
// that wrench read back by run --bag --wrench-topic as the measured force (measured_force.csv)
// and by calibrate as its record: all the same figure. A consumer that flips its sign fails here.
TEST(Cli, AxialForceHasOneSignInEveryReport) {
  const fs::path out = freshDir("axial");
  const std::string bag = kSrc + "/test/data/bags/phantom_insertion_commands.bag";
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml";
  const fs::path sim_bag = out / "simulated.bag", merged = out / "merged.bag";
  const Result r = runTool("run " + scene + " --quiet --out '" + (out / "run").string() + "' --bag '" + bag +
                           "' --pose-topic needle/command_pose --out-bag '" + sim_bag.string() + "'");
  ASSERT_EQ(r.status, 0) << r.err;
  auto cols = readColumns(out / "run" / "timeseries.csv");
  ASSERT_FALSE(cols["needle_axial_force"].empty());
  double cutting = 0;  // mean over the cut (the tip 12-17 mm deep, 1 cm/s)
  int n = 0;
  for (size_t i = 0; i < cols["t"].size(); ++i) {
    const double t = std::stod(cols["t"][i]), f = std::stod(cols["needle_axial_force"][i]);
    if (t < 1.5 || t > 2.0) continue;
    EXPECT_LT(f, 0) << "t = " << t << ": the tissue resists the insertion";
    cutting += f, ++n;
  }
  ASSERT_GT(n, 400);
  cutting /= n;
  EXPECT_NEAR(cutting, -0.02, 0.005);
  std::ifstream in(out / "run" / "summary.json");
  const json j = json::parse(in);
  EXPECT_NEAR(j["needles"]["needle"]["axial_force"].get<double>(), std::stod(cols["needle_axial_force"].back()), 1e-12);

  // The wrench (stamped from the recording's start) against the column, step by step; then
  // commands and wrenches in one bag, as a recorded session with a force sensor would be.
  const std::string py = capture(
      "/usr/bin/python3 -c \"import rosbag; r = rosbag.Bag('" + bag + "'); t0 = r.get_start_time(); "
      "m = rosbag.Bag('" + merged.string() + "', 'w'); "
      "[m.write(tp, x, t) for tp, x, t in r.read_messages()]; n = 0; f = 0.0\n"
      "for _, w, _ in rosbag.Bag('" + sim_bag.string() + "').read_messages(['/needle_sim/needle/wrench']):\n"
      "    m.write('needle/wrench', w, w.header.stamp); s = w.header.stamp.to_sec() - t0\n"
      "    if 1.5 <= s <= 2.0: n += 1; f += w.wrench.force.x\n"
      "m.close(); print(n, f / n)\"");
  long wn = 0;
  double wrench = 0;
  std::istringstream(py) >> wn >> wrench;
  EXPECT_NEAR(wn, n, 2) << py;
  EXPECT_NEAR(wrench, cutting, 1e-3 * std::abs(cutting)) << py;

  // Read back as the measured force: measured and simulated agree, sign included.
  const Result b = runTool("run " + scene + " --quiet --out '" + (out / "replay").string() + "' --bag '" +
                           merged.string() + "' --pose-topic needle/command_pose --wrench-topic needle/wrench");
  ASSERT_EQ(b.status, 0) << b.err;
  auto m = readColumns(out / "replay" / "measured_force.csv");
  ASSERT_GT(m["t"].size(), 4000u);
  double worst = 0, measured = 0;
  int k = 0;
  for (size_t i = 0; i < m["t"].size(); ++i) {
    const double t = std::stod(m["t"][i]), fm = std::stod(m["measured_axial_force"][i]);
    worst = std::max(worst, std::abs(fm - std::stod(m["simulated_axial_force"][i])));
    if (t >= 1.5 && t <= 2.0) measured += fm, ++k;
  }
  // (The stamps carry the recording's epoch in a double: the samples sit up to 2e-7 s off the
  // steps, which the puncture's spike turns into 1e-5 N; a flipped sign would be 0.04 N.)
  EXPECT_LT(worst, 1e-4) << "measured and simulated axial force differ";
  ASSERT_GT(k, 400);
  EXPECT_NEAR(measured / k, cutting, 1e-3 * std::abs(cutting));

#ifdef NEEDLE_SIM_SANITIZED
  return;  // three more replays for calibrate: the regular build checks its sign
#endif
  // calibrate reads the same record: at the values that made it, the residual is tiny (a
  // flipped sign leaves twice the force).
  const Result c = runTool("calibrate " + scene + " --data '" + merged.string() +
                           "' --pose-topic needle/command_pose --wrench-topic needle/wrench --fit interaction.cutting_force "
                           "--max-evaluations 1 --no-plot --quiet --out '" + (out / "cal").string() + "'");
  ASSERT_EQ(c.status, 0) << c.err;
  std::ifstream cj(out / "cal" / "calibration.json");
  const json cal = json::parse(cj);
  EXPECT_LT(cal["rms_residual_start_n"].get<double>(), 0.05 * std::abs(cutting)) << cal.dump();
  auto fit = readColumns(out / "cal" / "fit.csv");
  ASSERT_FALSE(fit["t"].empty());
  for (size_t i = 0; i < fit["t"].size(); ++i)
    if (std::stod(fit["t"][i]) >= 1.5 && std::stod(fit["t"][i]) <= 2.0) {
      EXPECT_LT(std::stod(fit["measured"][i]), 0);
      EXPECT_LT(std::stod(fit["start"][i]), 0);
    }
}

// `needle_sim check --json` (doc/cli.md): the scene as the loader resolved it, for the Python
// to read instead of re-implementing `extends` and --set. phantom_insertion_16x8x8 extends
// phantom_insertion_8x4x4: its tree is the base's with its own name, description and cells;
// written out and checked again, that tree is the same scene.
TEST(Cli, CheckJsonIsTheSceneTheLoaderResolved) {
  const std::string scenes = kSrc + "/config/scenes/";
  const json fine = json::parse(capture("'" + kTool + "' check '" + scenes + "phantom_insertion_16x8x8.yaml' --json"));
  json base = json::parse(capture("'" + kTool + "' check '" + scenes + "phantom_insertion_8x4x4.yaml' --json"));
  EXPECT_EQ(fine["scene"]["tissue"]["grid"]["cells"], json::parse("[16, 8, 8]"));
  EXPECT_FALSE(fine["scene"].contains("extends"));
  EXPECT_EQ(fine["scene"]["tissue"]["material"]["young"], 1e7);  // the base's value, a number
  base["scene"]["tissue"]["grid"]["cells"] = fine["scene"]["tissue"]["grid"]["cells"];
  base["scene"]["name"] = fine["scene"]["name"];
  base["scene"]["description"] = fine["scene"]["description"];
  EXPECT_EQ(fine["scene"], base["scene"]);
  EXPECT_EQ(fine["needles"], base["needles"]);
  EXPECT_EQ(fine["needles"][0]["set_prefix"], "needle");
  EXPECT_EQ(fine["needles"][0]["planned_keyframe"], 1);  // advance 0.023, then withdrawn

  // --set applies after extends, as in the loader; the tree written out is the same scene.
  const std::string set = " --set tissue.grid.cells=[12,6,6] --set needle.base.position=[-0.04,0.01,0.011]";
  const json changed = json::parse(capture("'" + kTool + "' check '" + scenes + "phantom_insertion_16x8x8.yaml' --json" + set));
  EXPECT_EQ(changed["scene"]["tissue"]["grid"]["cells"], json::parse("[12, 6, 6]"));
  EXPECT_EQ(changed["needles"][0]["base_position"], json::parse("[-0.04, 0.01, 0.011]"));
  const fs::path out = freshDir("check_json");
  fs::create_directories(out);
  std::ofstream(out / "tree.yaml") << changed["scene"].dump();
  const json again = json::parse(capture("'" + kTool + "' check '" + (out / "tree.yaml").string() + "' --json"));
  EXPECT_EQ(again["scene"], changed["scene"]);
  for (const char* k : {"dofs", "elements", "steps", "needles", "targets"}) EXPECT_EQ(again[k], changed[k]) << k;
  EXPECT_EQ(changed["dofs"], 3 * 13 * 7 * 7 + 6 * 17);  // the 12x6x6 grid's nodes and the needle's

  // Invalid input: exit 2, nothing on stdout.
  EXPECT_EQ(runTool("check '" + scenes + "phantom_insertion_16x8x8.yaml' --json --set tissue.grid.cells=[0,1,1]").status, 2);
  EXPECT_EQ(capture("'" + kTool + "' check '" + scenes + "phantom_insertion_16x8x8.yaml' --json --set tissue.grid.cells=[0,1,1] 2>/dev/null"), "");
}

// `needle_sim check --aim` (doc/cli.md): the overrides that move the needles rigidly so that
// the first one's planned final tip, its deepest keyframe's (needle/trajectory_replan.hpp,
// not its largest advance), lands on the target. The needle here goes 10 mm in, then is
// pulled back 20 mm behind its start: its deepest keyframe is the last.
TEST(Cli, CheckAimPutsTheDeepestKeyframesTipOnTheTarget) {
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml";
  const std::string motion = " --set 'needle.motion=[{t: 0, advance: 0}, {t: 1, advance: 0.01}, {t: 3, advance: -0.02}]'";
  const double entry[3] = {-0.08, 0.0, 0.0}, target[3] = {-0.05, 0.01, 0.03};  // outside the box
  char aim[256];
  std::snprintf(aim, sizeof aim, " --aim %.17g %.17g %.17g %.17g %.17g %.17g", entry[0], entry[1], entry[2], target[0],
                target[1], target[2]);
  const json out = json::parse(capture("'" + kTool + "' check '" + scene + "'" + motion + aim));
  ASSERT_EQ(out["needles"][0]["planned_keyframe"], 2);
  ASSERT_EQ(out["aims"].size(), 1u);
  const json& a = out["aims"][0];
  EXPECT_EQ(a["reference"], "needle");
  std::string sets;
  for (const auto& s : a["set"]) sets += " --set '" + s.get<std::string>() + "'";
  ASSERT_EQ(a["set"].size(), 2u);  // base.position, base.direction (advance keyframes follow the base)

  // Checked again with the overrides: the planned final tip is on the target.
  const json moved = json::parse(capture("'" + kTool + "' check '" + scene + "'" + motion + sets + " --json"));
  ASSERT_TRUE(moved.contains("needles")) << sets;
  const json& n = moved["needles"][0];
  double axis_norm = 0, d[3], p[3];
  for (int i = 0; i < 3; ++i) {
    d[i] = n["base_direction"][i].get<double>();
    p[i] = n["base_position"][i].get<double>();
    axis_norm += (target[i] - entry[i]) * (target[i] - entry[i]);
    EXPECT_NEAR(n["planned_tip"][i].get<double>(), target[i], 1e-12) << i;
  }
  axis_norm = std::sqrt(axis_norm);
  // Along entry -> target; the deepest keyframe's tip (advance -0.02) on the target, the
  // largest advance's (0.01) 30 mm from it.
  double deepest = 0, largest = 0;
  for (int i = 0; i < 3; ++i) {
    EXPECT_NEAR(d[i], (target[i] - entry[i]) / axis_norm, 1e-15) << i;
    deepest += std::pow(p[i] + (0.032 - 0.02) * d[i] - target[i], 2);
    largest += std::pow(p[i] + (0.032 + 0.01) * d[i] - target[i], 2);
  }
  EXPECT_LT(std::sqrt(deepest), 1e-12);
  EXPECT_NEAR(std::sqrt(largest), 0.03, 1e-12);

  // Invalid aims: exit 2.
  EXPECT_EQ(runTool("check '" + scene + "' --aim 0 0 0 0 0 0").status, 2);          // entry = target
  EXPECT_EQ(runTool("check '" + scene + "' --aim 0 0 0 1 1").status, 2);            // five numbers
  EXPECT_EQ(runTool("check '" + scene + "' --aim 0 0 0 1 1 1 --aim-needles drill").status, 2);
  EXPECT_EQ(runTool("check '" + scene + "' --aim-needles needle").status, 2);        // without --aim
}

// run --assimilate: bad options and data are exit 2 naming the option; a measurement with a
// NaN row and a stale row is read with those counted, and the outputs carry an estimate per
// checkpoint, every sample's innovation and summary.json's assimilation section.
TEST(Cli, RunAssimilateRejectsBadInputsAndWritesItsOutputs) {
  const fs::path d = freshDir("assimilate");
  fs::create_directories(d);
  auto file = [&](const std::string& name, const std::string& text) {
    std::ofstream(d / name) << text;
    return (d / name).string();
  };
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml --set time.dt=0.002 --set time.duration=0.9";
  const std::string out = " --out '" + (d / "out").string() + "' --quiet";
  std::string csv = "t,axial_force\n";
  for (int i = 1; i <= 45; ++i) {
    char b[80];
    std::snprintf(b, sizeof b, "%.3f,%.6f\n", 0.02 * i, i < 20 ? 0.0 : -0.01 - 0.0005 * (i % 3));
    csv += b;
    if (i == 10) csv += "0.205,nan\n";
    if (i == 30) csv += "0.600,0.5\n";  // stale: the time of the row before
  }
  const std::string good = file("good.csv", csv);
  struct Case {
    std::string args, expect;
  };
  const std::vector<Case> cases = {
      {"--data '" + good + "'", "--assimilate"},
      {"--assimilate interaction.cutting_force", "--data"},
      {"--assimilate interaction.cutting_force --data '" + (d / "missing.csv").string() + "'", "cannot read"},
      {"--assimilate interaction.cutting_force --data '" + file("nocol.csv", "t,force\n0,1\n1,2\n") + "'", "axial_force"},
      {"--assimilate interaction.cutting_force --data '" + file("text.csv", "t,axial_force\n0,1\n1,abc\n") + "'", "finite"},
      {"--assimilate interaction.no_such_key --data '" + good + "'", "no_such_key"},
      {"--assimilate interaction.cutting_force --start interaction.friction=1 --data '" + good + "'", "not among the keys"},
      {"--assimilate interaction.cutting_force --noise -1 --data '" + good + "'", "--noise"},
      {"--assimilate interaction.cutting_force --noise 0.001 --data '" +
           file("both.csv", "t,axial_force,tip_x,tip_y,tip_z\n0.1,0,0,0.01,0.01\n0.2,0,0.001,0.01,0.01\n0.3,0,0.002,0.01,0.01\n") + "'",
       "--tip-noise"},
      {"--assimilate interaction.cutting_force --data '" + file("tip2.csv", "t,tip_x,tip_y\n0,0,0\n1,0,0\n") + "'", "tip_z"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.args);
    const Result r = runTool("run " + scene + " " + c.args + out);
    EXPECT_EQ(r.status, 2) << r.err;
    EXPECT_NE(r.err.find(c.expect), std::string::npos) << r.err;
  }
#ifdef NEEDLE_SIM_SANITIZED
  return;  // the estimator's dozens of runs are minutes under the sanitizers; the regular build runs them
#endif
  const Result r = runTool("run " + scene + " --assimilate interaction.cutting_force --noise 0.0005 --assimilate-every 0.3 "
                           "--data '" + good + "'" + out);
  ASSERT_EQ(r.status, 0) << r.err;
  const auto a = readColumns(d / "out" / "assimilation.csv");
  ASSERT_EQ(a.count("interaction.cutting_force_std"), 1u);
  ASSERT_EQ(a.count("interaction.cutting_force_roughness"), 1u);
  EXPECT_EQ(a.at("t").size(), 3u);  // 0.3, 0.6 and the record's end 0.9
  const auto inn = readColumns(d / "out" / "innovation.csv");
  EXPECT_EQ(inn.at("t").size(), 45u);
  std::ifstream sj(d / "out" / "summary.json");
  const nlohmann::json j = nlohmann::json::parse(sj);
  const auto& p = j.at("assimilation").at("parameters").at("interaction.cutting_force");
  EXPECT_NEAR(p.at("value").get<double>(), std::stod(a.at("interaction.cutting_force").back()), 1e-9);
  EXPECT_TRUE(p.at("std").is_number());
  EXPECT_TRUE(p.contains("roughness"));
  EXPECT_EQ(j.at("assimilation").at("rejected").at("nonfinite").get<int>(), 1);
  EXPECT_EQ(j.at("assimilation").at("rejected").at("stale").get<int>(), 1);
  EXPECT_EQ(j.at("status"), "ok");  // the run's own summary is still there
}

// run --bag with --assimilate from the node's other measurement topics: a tracked tip
// (PointStamped) and a shape sensor (PoseArray, the last pose at the tip) beside the wrench.
// The shipped session replayed with its hidden values (30 mN, 400 Pa) gives the needle's beam
// nodes (its --out-bag's path, 2 mm apart, 30 Hz); with 50 um of noise they are the shape,
// their last the tip. Read into rows of their own (channels axial_force, tip, shape), the
// estimate within 10 % of the hidden value and consistent with the three noises, each shape's
// innovation about its noise. The same tip, shapes and commanded poses in a tracker's frame,
// placed in the tissue frame by the bag's /tf_static: the same estimate. A shape in a frame the bag's tf does
// not know, a topic of another type or a shape without --assimilate: exit 2, naming it.
TEST(Cli, RunAssimilatesABagsTipAndShape) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "the estimator's runs of the whole session take minutes under the sanitizers";
#endif
  const fs::path d = freshDir("assimilate_bag_shape");
  const std::string scene = kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml --set time.dt=0.002";
  const std::string session = kSrc + "/data/examples/phantom_insertion_session.bag";
  const fs::path sim_bag = d / "patient.bag", merged = d / "merged.bag", world = d / "world.bag",
                 tracker = d / "tracker.bag";
  const Result p = runTool("run " + scene + " --set interaction.cutting_force=0.03 --set interaction.grip_pressure=400 --bag '" +
                           session + "' --pose-topic needle/command_pose --out-bag '" + sim_bag.string() + "' --quiet --out '" +
                           (d / "patient").string() + "'");
  ASSERT_EQ(p.status, 0) << p.err;
  const std::string py = capture(
      "/usr/bin/python3 -c \"import random, rosbag\n"
      "from geometry_msgs.msg import Pose, PoseArray, PointStamped, TransformStamped\n"
      "from tf2_msgs.msg import TFMessage\n"
      "import copy\n"
      "rng = random.Random(3); n = 0\n"
      "m = rosbag.Bag('" + merged.string() + "', 'w'); w = rosbag.Bag('" + world.string() + "', 'w')\n"
      "k = rosbag.Bag('" + tracker.string() + "', 'w'); first = None\n"
      "def tracked(p):  # tissue -> tracker: R^T (p - t), R a quarter turn about z\n"
      "    q = copy.deepcopy(p); x, y, z = p.x - 0.1, p.y + 0.05, p.z - 0.02; q.x, q.y, q.z = y, -x, z; return q\n"
      "def turned(q):  # R^T q: a quarter turn back about z\n"
      "    c = 0.7071067811865476; r = copy.deepcopy(q)\n"
      "    r.w, r.x, r.y, r.z = c * q.w + c * q.z, c * q.x + c * q.y, c * q.y - c * q.x, c * q.z - c * q.w; return r\n"
      "for tp, x, t in rosbag.Bag('" + session + "').read_messages():\n"
      "    m.write(tp, x, t); w.write(tp, x, t); first = first or t\n"
      "    if tp.lstrip('/') == 'needle/command_pose':\n"
      "        x = copy.deepcopy(x); x.header.frame_id = 'tracker'\n"
      "        x.pose.position = tracked(x.pose.position); x.pose.orientation = turned(x.pose.orientation)\n"
      "    k.write(tp, x, t)\n"
      "T = TransformStamped(); T.header.stamp = first; T.header.frame_id = 'tissue'; T.child_frame_id = 'tracker'\n"
      "T.transform.translation.x, T.transform.translation.y, T.transform.translation.z = 0.1, -0.05, 0.02\n"
      "T.transform.rotation.z, T.transform.rotation.w = 0.7071067811865476, 0.7071067811865476\n"
      "k.write('/tf_static', TFMessage([T]), first)\n"

      "for _, path, t in rosbag.Bag('" + sim_bag.string() + "').read_messages(['/needle_sim/needle/path']):\n"
      "    a = PoseArray(); a.header = path.header\n"
      "    for q in path.poses:\n"
      "        p = Pose(); p.orientation.w = 1.0\n"
      "        p.position.x, p.position.y, p.position.z = [c + rng.gauss(0, 5e-5) for c in (q.pose.position.x, q.pose.position.y, q.pose.position.z)]\n"
      "        a.poses.append(p)\n"
      "    tip = PointStamped(); tip.header = path.header; tip.point = a.poses[-1].position\n"
      "    m.write('needle/shape', a, path.header.stamp); m.write('needle/tip', tip, path.header.stamp); n += 1\n"
      "    b = copy.deepcopy(a); b.header.frame_id = 'tracker'\n"
      "    for p in b.poses: p.position = tracked(p.position)\n"
      "    u = copy.deepcopy(tip); u.header.frame_id = 'tracker'; u.point = tracked(tip.point)\n"
      "    k.write('needle/shape', b, path.header.stamp); k.write('needle/tip', u, path.header.stamp)\n"
      "    a.header.frame_id = 'world'; w.write('needle/shape', a, path.header.stamp)\n"
      "m.close(); w.close(); k.close(); print(n)\"");
  const int shapes = std::atoi(py.c_str());
  ASSERT_GT(shapes, 100) << py;
  const std::string topics = " --pose-topic needle/command_pose --wrench-topic needle/wrench --tip-topic needle/tip "
                             "--shape-topic needle/shape --shape-spacing 0.002";
  // Both hidden values (the grip from 150 Pa): with the grip at the scene's the force misfits (its RMS twice its
  // noise), which the shapes' many points that fit must not hide (consistent: false).
  const std::string estimate = " --assimilate interaction.cutting_force,interaction.grip_pressure --start interaction.grip_pressure=150 "
                               "--bounds interaction.grip_pressure=0:2000 --noise 0.0005 --tip-noise 5e-5 --shape-noise 5e-5 "
                               "--assimilate-every 10 --quiet --out '";
  const Result r = runTool("run " + scene + " --bag '" + merged.string() + "'" + topics + estimate + (d / "est").string() + "'");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream sj(d / "est" / "summary.json");
  const nlohmann::json j = nlohmann::json::parse(sj);
  const auto& a = j.at("assimilation");
  EXPECT_EQ(a.at("channels"), nlohmann::json({"axial_force", "tip", "shape"}));
  EXPECT_GT(a.at("samples").get<int>(), 479 + shapes / 2);  // the wrench's rows and most shapes' own
  EXPECT_TRUE(a.at("consistent").get<bool>());
  EXPECT_NEAR(a.at("parameters").at("interaction.cutting_force").at("value").get<double>(), 0.03, 0.003);
  EXPECT_NEAR(a.at("parameters").at("interaction.grip_pressure").at("value").get<double>(), 400, 40);
  auto in = readColumns(d / "est" / "innovation_shape.csv");
  ASSERT_GT(in["t"].size(), static_cast<size_t>(shapes / 2));
  std::vector<double> rms;
  for (const auto& v : in["innovation_rms"]) rms.push_back(std::stod(v));
  std::nth_element(rms.begin(), rms.begin() + rms.size() / 2, rms.end());
  EXPECT_NEAR(rms[rms.size() / 2], 5e-5, 2e-5);
  EXPECT_EQ(in["points"].front(), "17");
  // The cutting force alone from `bag` into DIR/`out`: its summary.json.
  const auto cuttingOnly = [&](const fs::path& bag, const std::string& out) {
    const Result r = runTool("run " + scene + " --bag '" + bag.string() + "'" + topics +
                             " --assimilate interaction.cutting_force --noise 0.0005 --tip-noise 5e-5 --shape-noise 5e-5 "
                             "--assimilate-every 10 --quiet --out '" + (d / out).string() + "'");
    EXPECT_EQ(r.status, 0) << r.err;
    std::ifstream f(d / out / "summary.json");
    return nlohmann::json::parse(f);
  };
  // The grip left at the scene's: the force's residuals are about twice its noise; among the
  // shapes' points, which fit, the pooled RMS is not.
  const nlohmann::json o = cuttingOnly(merged, "one");
  EXPECT_FALSE(o.at("assimilation").at("consistent").get<bool>()) << o.at("assimilation").dump();
  // The same measurements and commanded poses in a tracker's frame, which the bag's
  // /tf_static places in the tissue frame: the same estimate (they differ from the first
  // bag's by round-off).
  const nlohmann::json kk = cuttingOnly(tracker, "k");
  const auto value = [](const nlohmann::json& x) {
    return x.at("assimilation").at("parameters").at("interaction.cutting_force").at("value").get<double>();
  };
  EXPECT_NEAR(value(kk), value(o), 1e-6 * value(o));
  for (const auto& [args, why] : std::vector<std::pair<std::string, std::string>>{
           {" --bag '" + world.string() + "' --pose-topic needle/command_pose --wrench-topic needle/wrench --shape-topic "
                "needle/shape --shape-spacing 0.002" + estimate + (d / "w").string() + "'", "tissue frame"},
           {" --bag '" + merged.string() + "' --pose-topic needle/command_pose --shape-topic needle/tip" + estimate +
                (d / "t").string() + "'", "not geometry_msgs/PoseArray"},
           {" --bag '" + merged.string() + "' --pose-topic needle/command_pose --shape-topic needle/shape --quiet --out '" +
                (d / "n").string() + "'", "--assimilate"}}) {
    const Result b = runTool("run " + scene + args);
    EXPECT_EQ(b.status, 2) << args;
    EXPECT_NE(b.err.find(why), std::string::npos) << args << ": " << b.err;
  }
}

// run --bag with --assimilate and no --data: the bag's wrench is the measurement and its
// commanded poses drive the estimator's runs, for as long as the record (not the scene's
// duration). The shipped session (cutting 30 mN, grip 400 Pa, 0.5 mN of noise).
TEST(Cli, RunAssimilatesABagsWrench) {
#ifdef NEEDLE_SIM_SANITIZED
  GTEST_SKIP() << "the estimator's runs of the whole session take minutes under the sanitizers";
#endif
  const fs::path d = freshDir("assimilate_bag");
  const Result r = runTool("run " + kSrc + "/config/scenes/phantom_insertion_8x4x4.yaml --set time.dt=0.002 --bag " + kSrc +
                           "/data/examples/phantom_insertion_session.bag --pose-topic needle/command_pose --wrench-topic "
                           "needle/wrench --assimilate interaction.cutting_force --noise 0.0005 --assimilate-every 2.5 "
                           "--out '" + d.string() + "' --quiet");
  ASSERT_EQ(r.status, 0) << r.err;
  std::ifstream sj(d / "summary.json");
  const nlohmann::json j = nlohmann::json::parse(sj);
  const auto& a = j.at("assimilation");
  EXPECT_EQ(a.at("samples").get<int>(), 479);
  EXPECT_EQ(a.at("checkpoints").get<int>(), 2);
  EXPECT_NEAR(a.at("parameters").at("interaction.cutting_force").at("value").get<double>(), 0.03, 0.003);
}
