#pragma once
// Marking strategies (in the spirit of MFEM's ThresholdRefiner): which elements to refine
// given the element error indicators eta_e.
//  - MaxMarking (the paper's rule, eq. "max rule"): eta_e >= theta * max eta;
//  - BulkMarking (Doerfler): the smallest set of largest indicators whose squared sum
//    reaches theta * sum eta^2.
// Both skip elements that may not be refined (at max_level); the maximum (max rule) and the
// total (bulk rule) are over all elements, so refinement stops once the largest errors sit
// in elements at max_level.
#include <memory>
#include <string>
#include <vector>

namespace needle_sim {

class Marking {
 public:
  virtual ~Marking() = default;
  // Elements to refine; refinable[e] == false excludes element e.
  virtual std::vector<int> mark(const std::vector<double>& eta, const std::vector<char>& refinable) const = 0;
};

class MaxMarking : public Marking {
 public:
  explicit MaxMarking(double theta) : theta_(theta) {}
  std::vector<int> mark(const std::vector<double>& eta, const std::vector<char>& refinable) const override;

 private:
  double theta_;
};

class BulkMarking : public Marking {
 public:
  explicit BulkMarking(double theta) : theta_(theta) {}
  std::vector<int> mark(const std::vector<double>& eta, const std::vector<char>& refinable) const override;

 private:
  double theta_;
};

}  // namespace needle_sim
