#include "needle_sim/solver/dof_map.hpp"

#include <functional>
#include <map>
#include <stdexcept>

namespace needle_sim {

DofMap::DofMap(const std::vector<char>& prescribed) { build(prescribed, nullptr); }

DofMap::DofMap(const std::vector<char>& prescribed, const std::vector<std::vector<std::pair<int, double>>>& hanging) {
  build(prescribed, &hanging);
}

void DofMap::build(const std::vector<char>& prescribed,
                   const std::vector<std::vector<std::pair<int, double>>>* hanging) {
  const int n = static_cast<int>(prescribed.size());
  prescribed_ = prescribed;
  free_of_full_.assign(n, -1);
  full_of_free_.clear();
  auto isHanging = [&](int i) { return hanging && !prescribed[i] && !(*hanging)[i].empty(); };
  for (int i = 0; i < n; ++i)
    if (!prescribed[i] && !isHanging(i)) {
      free_of_full_[i] = static_cast<int>(full_of_free_.size());
      full_of_free_.push_back(i);
    }
  // Rows of P; hanging rows expanded recursively (a master may itself hang).
  std::vector<std::map<int, double>> rows(n);
  std::vector<char> state(n, 0);  // 0 todo, 1 in progress, 2 done
  std::function<void(int)> expand = [&](int i) {
    if (state[i] == 2) return;
    if (state[i] == 1) throw std::invalid_argument("DofMap: cyclic hanging-node constraints");
    state[i] = 1;
    if (free_of_full_[i] >= 0) {
      rows[i][free_of_full_[i]] = 1.0;
    } else if (isHanging(i)) {
      for (const auto& [m, w] : (*hanging)[i]) {
        expand(m);
        for (const auto& [f, wf] : rows[m]) rows[i][f] += w * wf;
      }
      hanging_order_.push_back(i);
    }
    state[i] = 2;
  };
  offset_.assign(n + 1, 0);
  entries_.clear();
  hanging_order_.clear();
  hanging_.clear();
  if (hanging) hanging_ = *hanging;
  for (int i = 0; i < n; ++i) {
    expand(i);
    for (const auto& [f, w] : rows[i]) entries_.push_back({f, w});
    offset_[i + 1] = static_cast<int>(entries_.size());
  }
}

void DofMap::gather(const VecX& full, VecX& free) const {
  free.setZero(numFree());
  for (int i = 0; i < numFull(); ++i)
    for (const DofWeight* e = expansionBegin(i); e != expansionEnd(i); ++e) free[e->free] += e->weight * full[i];
}

void DofMap::scatter(const VecX& free, VecX& full) const {
  full.setZero(numFull());
  for (int i = 0; i < numFull(); ++i) {
    double v = 0;
    for (const DofWeight* e = expansionBegin(i); e != expansionEnd(i); ++e) v += e->weight * free[e->free];
    full[i] = v;
  }
}

}  // namespace needle_sim

namespace needle_sim {
void DofMap::interpolateHanging(VecX& full) const {
  for (int i : hanging_order_) {
    double v = 0;
    for (const auto& [m, w] : hanging_[i]) v += w * full[m];
    full[i] = v;
  }
}
}  // namespace needle_sim
