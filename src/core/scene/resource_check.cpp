#include "needle_sim/scene/resource_check.hpp"

#include <unistd.h>

#include <cmath>
#include <sstream>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

double estimateSolverBytes(const Vec3i& cells) {
  const double nodes = double(cells[0] + 1) * (cells[1] + 1) * (cells[2] + 1);
  const double elements = double(cells[0]) * cells[1] * cells[2];
  const double dofs = 3 * nodes;
  // Factor fill of a 3D grid under nested dissection grows like n^(4/3); scaled from the
  // 28,611-DOF phantom (14.5 M nonzeros, doc/benchmarks.md "Linear solver").
  const double lnz = 14.5e6 * std::pow(dofs / 28611.0, 4.0 / 3.0);
  const double matrix = 81.0 / 2 * dofs * 12;     // upper triangle, value + index
  const double positions = elements * 576 * 4.0;  // assembly scatter map
  const double vectors = dofs * 8 * 30;
  return 8 * 1.5 * lnz + matrix + positions + vectors;
}

void checkSolverMemory(const Vec3i& cells, const std::string& file, const std::string& key) {
  const double need = estimateSolverBytes(cells);
  const double have = double(sysconf(_SC_PHYS_PAGES)) * double(sysconf(_SC_PAGE_SIZE));
  if (need > 0.6 * have) {
    std::ostringstream m;
    m.precision(3);
    m << "grid of " << double(cells[0]) * cells[1] * cells[2] << " cells needs an estimated " << need / (1 << 30)
      << " GiB, more than 60% of this machine's " << have / (1 << 30) << " GiB";
    throw InputError(file, key, m.str());
  }
}

}  // namespace needle_sim
