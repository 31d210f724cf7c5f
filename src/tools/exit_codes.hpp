#pragma once
// The tool's exit statuses shared by its commands (doc/cli.md): bad input (scene, options,
// files) and a numerical failure.
namespace needle_sim_tool {
constexpr int kExitInput = 2;
constexpr int kExitNumerical = 3;
}  // namespace needle_sim_tool
