#pragma once
// Error types shared by the whole core library.
//
// Two kinds of failure matter to users and map to the tool's exit status:
//  - InputError: a scene file, mesh or parameter is invalid. Raised before any
//    simulation work, naming the file, the key and the problem (exit status 2).
//  - NumericalError: the simulation itself failed (NaN/Inf, divergence, a
//    matrix that is not positive definite). Raised with the step (exit status 3).
#include <stdexcept>
#include <string>

namespace needle_sim {

class InputError : public std::runtime_error {
 public:
  InputError(const std::string& file, const std::string& key, const std::string& problem)
      : std::runtime_error(compose(file, key, problem)), file_(file), key_(key), problem_(problem) {}
  const std::string& file() const { return file_; }
  const std::string& key() const { return key_; }
  const std::string& problem() const { return problem_; }

 private:
  static std::string compose(const std::string& file, const std::string& key,
                             const std::string& problem) {
    std::string s;
    if (!file.empty()) s += file + ": ";
    if (!key.empty()) s += "'" + key + "': ";
    return s + problem;
  }
  std::string file_, key_, problem_;
};

class NumericalError : public std::runtime_error {
 public:
  NumericalError(long step, const std::string& what)
      : std::runtime_error(what), step_(step) {}
  long step() const { return step_; }

 private:
  long step_;
};

}  // namespace needle_sim
