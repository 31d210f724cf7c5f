// libFuzzer target: triangle-mesh loading (assimp) and what is built on a loaded surface:
// closedness and orientation checks, the winding-number inside test and a small immersed
// grid (issue #8). The first byte picks the format (OBJ, STL, OFF, PLY); the rest is the
// file. Every input must either load or raise InputError; anything else is a bug.
//
//   scripts/fuzz.sh --seconds 60
//   build/devel/lib/needle_sim/fuzz_mesh_replay test/data/fuzz/mesh
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <memory>
#include <stdexcept>
#include <string>

#include "needle_sim/core/error.hpp"
#include "needle_sim/geometry/immersed_grid.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  static const char* kExt[] = {".obj", ".stl", ".off", ".ply"};
  const std::string path = "/tmp/needle_sim_fuzz_mesh_" + std::to_string(getpid()) + kExt[data[0] % 4];
  {
    std::ofstream f(path, std::ios::binary);
    f.write(reinterpret_cast<const char*>(data + 1), static_cast<std::streamsize>(size - 1));
  }
  try {
    needle_sim::SurfaceTransform t;
    auto mesh = std::make_shared<const needle_sim::TriangleMesh>(needle_sim::loadTriangleMesh(path, t, "", "fuzz"));
    needle_sim::ImmersedGridSettings g;
    g.cells = needle_sim::Vec3i(4, 4, 4);
    g.samples = 2;
    needle_sim::ImmersedGrid grid(mesh, g);
    (void)grid.mesh().numElements();
  } catch (const needle_sim::InputError&) {
  } catch (const std::invalid_argument&) {
    // A closed but degenerate surface (no volume): the simulation turns this into an
    // InputError on tissue.geometry.
  }
  std::remove(path.c_str());
  return 0;
}
