#pragma once
// `needle_sim check`: a scene loaded, validated and its mesh built, without running it
// (doc/cli.md). With --json, what the loader made of the scene as JSON on stdout, for the
// Python (the ensemble's trajectories, the studies) to read instead of re-implementing it:
// the YAML tree after `extends` and --set, the needles with their --set prefixes and planned
// final tips (needle/trajectory_replan.hpp's rule), the targets and probes. With --aim, the
// --set overrides that move needles rigidly, as one tool, onto a line entry -> target
// (rigidAim). Plain `check` then times a pre-flight (sim/preflight.hpp): whether the scene
// keeps real time on this machine, with what margin.
#include <string>
#include <vector>

struct CheckOptions {
  std::string scene;
  std::vector<std::string> sets;
  bool json = false;
  std::vector<double> aims;                // 6 numbers an aim: entry x y z, target x y z [m]
  std::vector<std::string> aim_needles;    // the needles moved (default: all), in scene order
  double preflight = -1;                   // pre-flight wall budget [s]; < 0: 2 s, 0 with --json or --aim
};

// Exit status 0, or 2 on invalid input (the message on stderr).
int checkCommand(const CheckOptions& opts);
