#pragma once
// `needle_sim soak`: a long run of a scene with a scripted back-and-forth insertion of its
// first needle (insert, hold, withdraw, hold, repeated), recording no per-step data, so that
// what grows is the simulation's own memory: resident set size and step time per window,
// non-finite state or divergence (the run stops with exit status 3), energy per window.
#include <string>
#include <vector>

struct SoakOptions {
  std::string scene;
  std::vector<std::string> sets;
  long steps = 100000;
  long window = 0;           // steps per reported window (0: one cycle, so windows end at the same phase)
  double depth = 0.02;       // insertion depth of a cycle beyond the start pose [m]
  double speed = 0.01;       // [m/s]
  double hold = 0.25;        // hold at depth and at the start [s]
  double max_growth_mb = 0;  // exit 1 if the heap in use grows more than this from the 2nd window to the last full one (0: off)
  std::string csv;           // per-window rows
  std::string json_out;
};

int soakCommand(const SoakOptions& opts);
