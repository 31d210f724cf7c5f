#include "needle_sim/tissue/compliance_cache.hpp"

#include <algorithm>

#include "needle_sim/solver/cholmod_solver.hpp"

namespace needle_sim {

void ComplianceCache::prepare(const std::vector<int>& free_dofs, const CholmodSolver& factor, long version,
                              int num_free) {
  std::vector<int> todo;
  std::vector<std::pair<long, int>> stale;
  for (int f : free_dofs) {
    auto it = columns_.find(f);
    if (it == columns_.end()) todo.push_back(f);
    else if (it->second.version != version) stale.emplace_back(it->second.version, f);
  }
  // Evict columns no longer in use once the cache is much larger than the working set.
  if (columns_.size() > 2 * (free_dofs.size() + keep_.size()) + 64) {
    std::unordered_map<int, Column> kept;
    for (const std::vector<int>* set : {&free_dofs, static_cast<const std::vector<int>*>(&keep_)})
      for (int f : *set) {
        auto it = columns_.find(f);
        if (it != columns_.end()) kept.emplace(f, std::move(it->second));
      }
    columns_ = std::move(kept);
  }
  solved_new_ += static_cast<long>(todo.size());
  std::sort(stale.begin(), stale.end());
  for (size_t k = 0; k < stale.size() && k < static_cast<size_t>(kRefresh); ++k) todo.push_back(stale[k].second);
  if (todo.empty()) return;
  Eigen::MatrixXd E = Eigen::MatrixXd::Zero(num_free, static_cast<Eigen::Index>(todo.size()));
  for (size_t j = 0; j < todo.size(); ++j) E(todo[j], static_cast<Eigen::Index>(j)) = 1.0;
  Eigen::MatrixXd X;
  factor.solve(E, X);
  for (size_t j = 0; j < todo.size(); ++j) columns_[todo[j]] = {X.col(static_cast<Eigen::Index>(j)), version};
}

std::vector<int> ComplianceCache::dofs() const {
  std::vector<int> d;
  d.reserve(columns_.size());
  for (const auto& [f, c] : columns_) d.push_back(f);
  std::sort(d.begin(), d.end());
  return d;
}

void ComplianceCache::adopt(const std::vector<int>& dofs, const Eigen::MatrixXd& X, long version) {
  for (size_t j = 0; j < dofs.size(); ++j) columns_[dofs[j]] = {X.col(static_cast<Eigen::Index>(j)), version};
}

}  // namespace needle_sim
