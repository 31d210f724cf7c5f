#include "check.hpp"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <stdexcept>

#include "needle_sim/core/error.hpp"
#include "needle_sim/needle/trajectory_replan.hpp"
#include "needle_sim/scene/scene_check.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/scene/scene_overrides.hpp"
#include "needle_sim/sim/live_loop.hpp"
#include "needle_sim/sim/preflight.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "exit_codes.hpp"

using namespace needle_sim;
using needle_sim_tool::kExitInput;
using Json = nlohmann::ordered_json;  // the scene's keys in the file's order

namespace {

// The scene's YAML tree as the loader builds from it (scene_loader.cpp): the file, its
// `extends` chain resolved, then the overrides in order. Called after loadScene accepted the
// same file and overrides.
YAML::Node resolvedTree(const std::string& path, const std::vector<std::string>& sets) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  YAML::Node root = resolveExtends(YAML::Load(ss.str()), path);
  for (const auto& s : sets) applyOverride(root, s, path);
  return root;
}

// A plain scalar as the loader reads it: a number where yaml-cpp reads one (the loader's
// as<long long>, as<double>), true/false, null; anything else, and every quoted scalar, a string.
Json scalarJson(const YAML::Node& n) {
  const std::string& s = n.Scalar();
  if (n.Tag() != "?") return s;  // quoted or explicitly tagged
  if (s == "~" || s == "null" || s == "Null" || s == "NULL") return nullptr;
  if (s == "true" || s == "True" || s == "TRUE") return true;
  if (s == "false" || s == "False" || s == "FALSE") return false;
  long long i;
  if (YAML::convert<long long>::decode(n, i)) return i;
  double d;
  if (YAML::convert<double>::decode(n, d) && std::isfinite(d)) return d;
  return s;
}

Json treeJson(const YAML::Node& n) {
  switch (n.Type()) {
    case YAML::NodeType::Map: {
      Json out = Json::object();
      for (const auto& kv : n) out[kv.first.Scalar()] = treeJson(kv.second);
      return out;
    }
    case YAML::NodeType::Sequence: {
      Json out = Json::array();
      for (const auto& v : n) out.push_back(treeJson(v));
      return out;
    }
    case YAML::NodeType::Scalar:
      return scalarJson(n);
    default:
      return nullptr;
  }
}

Json vec(const Vec3& v) { return Json::array({v[0], v[1], v[2]}); }

// "key=[x,y,z]" with every digit a double needs to come back the same (nlohmann's shortest
// round trip).
std::string setVec(const std::string& key, const Vec3& v) { return key + "=" + vec(v).dump(); }

// What --set calls needle i: `needle` (a scene with one `needle:`) or `needles.<i>`.
std::string needlePrefix(const YAML::Node& tree, size_t i) {
  return tree["needles"] ? "needles." + std::to_string(i) : "needle";
}

YAML::Node needleNode(const YAML::Node& tree, size_t i) {
  return tree["needles"] ? YAML::Node(tree["needles"][i]) : YAML::Node(tree["needle"]);
}

Json needlesJson(const Scene& scene, const YAML::Node& tree) {
  Json out = Json::array();
  for (size_t i = 0; i < scene.needles.size(); ++i) {
    const NeedleScene& n = scene.needles[i];
    const PlannedTip p = plannedFinalTip(n);
    out.push_back({{"name", n.name},
                   {"set_prefix", needlePrefix(tree, i)},
                   {"length", n.length},
                   {"base_position", vec(n.base_position)},
                   {"base_direction", vec(n.base_direction)},
                   {"rest_tip", vec(p.rest_tip)},
                   {"planned_tip", vec(p.tip)},
                   {"planned_keyframe", p.keyframe >= 0 ? Json(p.keyframe) : Json(nullptr)}});
  }
  return out;
}

// The needles an aim moves, in scene order (the first is the reference).
std::vector<size_t> movedNeedles(const Scene& scene, const CheckOptions& o) {
  std::string names;
  for (const auto& n : scene.needles) names += (names.empty() ? "" : ", ") + n.name;
  if (scene.needles.empty()) throw InputError(scene.file, "--aim", "the scene has no needle to aim");
  for (const auto& w : o.aim_needles)
    if (std::none_of(scene.needles.begin(), scene.needles.end(), [&](const NeedleScene& n) { return n.name == w; }))
      throw InputError(scene.file, "--aim-needles", "the scene has no needle '" + w + "' (it has " + names + ")");
  std::vector<size_t> moved;
  for (size_t i = 0; i < scene.needles.size(); ++i)
    if (o.aim_needles.empty() ||
        std::find(o.aim_needles.begin(), o.aim_needles.end(), scene.needles[i].name) != o.aim_needles.end())
      moved.push_back(i);
  return moved;
}

// One --aim: the overrides that move the needles rigidly so that the reference's planned
// final tip lands on the target, its axis along entry -> target; full-pose keyframes move
// with them (`advance` keyframes follow their base).
Json aimJson(const Scene& scene, const YAML::Node& tree, const std::vector<size_t>& moved, const Vec3& entry,
             const Vec3& target) {
  const NeedleScene& ref = scene.needles[moved.front()];
  RigidAim aim;
  try {
    aim = rigidAim(ref, entry, target);
  } catch (const std::invalid_argument& e) {
    throw InputError(scene.file, "--aim", e.what());
  }
  Json sets = Json::array(), names = Json::array();
  for (size_t i : moved) {
    const NeedleScene& n = scene.needles[i];
    const NeedleParameters m = rigidlyMoved(n, aim);
    const std::string p = needlePrefix(tree, i);
    names.push_back(n.name);
    sets.push_back(setVec(p + ".base.position", m.base_position));
    sets.push_back(setVec(p + ".base.direction", m.base_direction));
    const YAML::Node motion = needleNode(tree, i)["motion"];
    for (size_t k = 0; k < m.motion.size(); ++k) {
      if (!motion[k]["position"]) continue;
      const std::string q = p + ".motion." + std::to_string(k);
      sets.push_back(setVec(q + ".position", m.motion[k].position));
      sets.push_back(setVec(q + ".direction", m.motion[k].direction));
    }
  }
  const PlannedTip p = plannedFinalTip(ref);
  return {{"entry", vec(entry)},
          {"target", vec(target)},
          {"needles", names},
          {"reference", ref.name},
          {"planned_tip", vec(p.tip)},
          {"angle_deg", aim.angle() * 180 / M_PI},
          {"entry_target_distance", (target - entry).norm()},
          {"start_target_distance", (p.tip - p.rest_tip).norm()},
          {"set", sets}};
}

}  // namespace

int checkCommand(const CheckOptions& o) {
  try {
    if (!o.aim_needles.empty() && o.aims.empty()) throw InputError(o.scene, "--aim-needles", "needs --aim");
    if (o.aims.size() % 6 != 0)
      throw InputError(o.scene, "--aim", "expected 6 numbers an aim (entry x y z, target x y z), got " +
                                             std::to_string(o.aims.size()));
    for (double v : o.aims)
      if (!std::isfinite(v)) throw InputError(o.scene, "--aim", "expected finite numbers");
    Scene scene = loadScene(o.scene, o.sets);
    for (const std::string& w : sceneWarnings(scene)) std::cerr << "needle_sim: warning: " << w << '\n';
    // The pre-flight times the node's loop (sim/live_loop.hpp): what it states is the node's.
    applyLiveLoop(scene);
    Simulation sim(scene);
    const bool machine = o.json || !o.aims.empty();
    const double budget = o.preflight >= 0 ? o.preflight : (machine ? 0.0 : 2.0);
    if (!machine) {
      std::printf("%s: ok (%d dofs, %d elements, %ld steps)\n", o.scene.c_str(), sim.numDofs(), sim.numElements(),
                  scene.numSteps());
      std::fflush(stdout);
      if (budget > 0) std::printf("%s\n", preflight(sim, scene, {budget}).summary().c_str());
      return 0;
    }
    const YAML::Node tree = resolvedTree(o.scene, o.sets);
    Json out = {{"file", o.scene}, {"name", scene.name}, {"dofs", sim.numDofs()}, {"elements", sim.numElements()},
                {"steps", scene.numSteps()}, {"scene", treeJson(tree)}, {"needles", needlesJson(scene, tree)}};
    Json targets = Json::array(), probes = Json::array();
    for (size_t i = 0; i < scene.targets.size(); ++i)
      targets.push_back({{"name", scene.targets[i].name}, {"set_prefix", "targets." + std::to_string(i)},
                         {"point", vec(scene.targets[i].point)}});
    for (size_t i = 0; i < scene.probes.size(); ++i)
      probes.push_back({{"name", scene.probes[i].name}, {"set_prefix", "probes." + std::to_string(i)},
                        {"point", vec(scene.probes[i].point)}});
    out["targets"] = targets;
    out["probes"] = probes;
    if (budget > 0) {
      const PreflightResult p = preflight(sim, scene, {budget});
      out["preflight"] = {{"steps", p.steps},           {"scene_steps", p.scene_steps}, {"t_end", p.t_end},
                          {"dt", p.dt},                 {"step_median_ms", p.median_ms}, {"step_p999_ms", p.p999_ms},
                          {"step_max_ms", p.max_ms},    {"over_dt", p.over_dt},         {"max_dofs", p.max_dofs},
                          {"keeps_real_time", p.keepsRealTime()}, {"margin", p.margin()}, {"failure", p.failure},
                          {"summary", p.summary()}};
    }
    if (!o.aims.empty()) {
      const std::vector<size_t> moved = movedNeedles(scene, o);
      Json aims = Json::array();
      for (size_t a = 0; a < o.aims.size(); a += 6)
        aims.push_back(aimJson(scene, tree, moved, Vec3(o.aims[a], o.aims[a + 1], o.aims[a + 2]),
                               Vec3(o.aims[a + 3], o.aims[a + 4], o.aims[a + 5])));
      out["aims"] = aims;
    }
    std::printf("%s\n", out.dump(2).c_str());
    return 0;
  } catch (const InputError& e) {
    std::cerr << "needle_sim: invalid input: " << e.what() << '\n';
    return kExitInput;
  }
}
