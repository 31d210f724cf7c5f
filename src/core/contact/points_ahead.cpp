// Where each cutting needle's next constraint points will be embedded (rest space), for the
// compliance columns computed ahead of them (NeedleTissueInteraction::pointsAhead;
// doc/method.md "Constraint solve", compliance columns).
#include <algorithm>

#include "needle_sim/contact/needle_tissue_interaction.hpp"

namespace needle_sim {

std::vector<Vec3> NeedleTissueInteraction::pointsAhead() const {
  std::vector<Vec3> out;
  const double sp = settings_.shaft_spacing;
  for (size_t n = 0; n < tracks_.size(); ++n) {
    const Track& tr = tracks_[n];
    if (!tr.has_path || (tr.state != InsertionState::Punctured && tr.state != InsertionState::Inserted)) continue;
    if (!needles_[n]->bevel().enabled) out.push_back(tr.next_shaft_rest);
    if (tr.path.size() < 2) continue;
    const Vec3 d = (tr.path.back() - tr.path[tr.path.size() - 2]).normalized();
    const Vec3 u = d.unitOrthogonal(), v = d.cross(u), c = tr.path.back() + 0.5 * sp * d;
    out.push_back(c);
    for (const Vec3& w : {u, Vec3(-u), v, Vec3(-v)}) out.push_back(c + 0.25 * sp * w);
    out.push_back(tr.path.back() + sp * d);
  }
  return out;
}

std::vector<int> NeedleTissueInteraction::elementsAhead() const {
  std::vector<int> out;
  EmbeddedPoint ep;
  for (const Vec3& p : pointsAhead())
    if (rest_locator_->locate(p, ep)) out.push_back(ep.element);
  std::sort(out.begin(), out.end());
  out.erase(std::unique(out.begin(), out.end()), out.end());
  return out;
}

}  // namespace needle_sim
