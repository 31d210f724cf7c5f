#include "needle_sim/solver/dof_map.hpp"

namespace needle_sim {

DofMap::DofMap(const std::vector<char>& prescribed) : free_of_full_(prescribed.size(), -1) {
  for (size_t i = 0; i < prescribed.size(); ++i)
    if (!prescribed[i]) {
      free_of_full_[i] = static_cast<int>(full_of_free_.size());
      full_of_free_.push_back(static_cast<int>(i));
    }
}

void DofMap::gather(const VecX& full, VecX& free) const {
  free.resize(numFree());
  for (int k = 0; k < numFree(); ++k) free[k] = full[full_of_free_[k]];
}

void DofMap::scatter(const VecX& free, VecX& full) const {
  full.setZero(numFull());
  for (int k = 0; k < numFree(); ++k) full[full_of_free_[k]] = free[k];
}

}  // namespace needle_sim
