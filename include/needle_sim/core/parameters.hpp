#pragma once
// Parameters declared once (deal.II's ParameterHandler, bound to the settings structs). Each
// module's settings header declares its struct's keys — type, unit, admissible range, a
// one-line description; the default is the struct's own — in one `parameters()` table. From
// that table:
//   - the scene loader reads and checks the keys (scene/parameter_reader.hpp);
//   - settings built in code are checked by validate() (a Scene made in a test or a tool);
//   - doc/scene_format.md's key tables are generated (`needle_sim keys --markdown`; a test
//     fails when the committed page is not current);
//   - `needle_sim calibrate` takes a key's bounds from its range.
// Rules that tie several keys together (an inner radius below the outer one, the coarsening
// threshold below half the marking one) stay with the module, in its own check.
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <optional>
#include <type_traits>
#include <utility>
#include <string>
#include <vector>

#include "needle_sim/core/error.hpp"
#include "needle_sim/core/types.hpp"

namespace needle_sim {

// An interval of admissible values (for integers too); infinite ends are open.
struct Range {
  double lo = -std::numeric_limits<double>::infinity(), hi = std::numeric_limits<double>::infinity();
  bool lo_closed = false, hi_closed = false;

  static Range any() { return {}; }
  static Range positive() { return {0.0, std::numeric_limits<double>::infinity(), false, false}; }
  static Range nonNegative() { return {0.0, std::numeric_limits<double>::infinity(), true, false}; }
  static Range closed(double a, double b) { return {a, b, true, true}; }
  static Range open(double a, double b) { return {a, b, false, false}; }
  static Range openClosed(double a, double b) { return {a, b, false, true}; }
  static Range closedOpen(double a, double b) { return {a, b, true, false}; }
  static Range atLeast(double a) { return {a, std::numeric_limits<double>::infinity(), true, false}; }

  bool contains(double v) const {
    if (std::isnan(v)) return false;
    return (lo_closed ? v >= lo : v > lo) && (hi_closed ? v <= hi : v < hi);
  }
  // "> 0", ">= 1", "< 1", "(0, 0.5)", "[1, 100000]", "any"
  std::string text() const;
  static std::string number(double v);
};

enum class ParameterKind { Real, Integer, Flag, Vector, Choice, Text };

// What a key is, as the docs and calibrate read it.
struct ParameterDeclaration {
  std::string key;  // relative to its section, dotted: "material.young"
  ParameterKind kind = ParameterKind::Real;
  std::string unit;  // SI: "Pa", "m", "s", "N", "m/s^2"; "" for a pure number
  Range range;       // Real and Integer
  std::vector<std::string> choices;  // Choice: the names, in the enum's order
  bool required = false;
  std::string description;
  std::string default_text;  // the struct's default ("" for none: a required key, an absent optional)
  std::string type() const;   // "number", "integer", "bool", "[x, y, z]", "one of a, b", "string"
};

template <class S>
class Parameters {
 public:
  struct Entry {
    ParameterDeclaration declaration;
    // The member, as a pointer into a settings struct (its type follows the kind: double,
    // int, bool, Vec3, std::string, or an enum read and written through as_int/set_int).
    std::function<void*(S&)> field;
    std::function<int(const void*)> as_int;     // Choice
    std::function<void(void*, int)> set_int;    // Choice
    bool optional_real = false;                 // a std::optional<double> member
  };

  // f: S& -> double& (a member, possibly nested: [](S& s) -> double& { return s.material.young; }).
  template <class F>
  Parameters& real(std::string key, F f, std::string unit, Range range, std::string description, bool required = false) {
    entries_.push_back({decl(std::move(key), ParameterKind::Real, std::move(unit), range, std::move(description), required),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, false});
    return *this;
  }
  // f: S& -> std::optional<double>& (absent unless the scene gives it).
  template <class F>
  Parameters& optionalReal(std::string key, F f, std::string unit, Range range, std::string description) {
    entries_.push_back({decl(std::move(key), ParameterKind::Real, std::move(unit), range, std::move(description), false),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, true});
    return *this;
  }
  template <class F>
  Parameters& integer(std::string key, F f, Range range, std::string description, bool required = false) {
    entries_.push_back({decl(std::move(key), ParameterKind::Integer, "", range, std::move(description), required),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, false});
    return *this;
  }
  template <class F>
  Parameters& flag(std::string key, F f, std::string description) {
    entries_.push_back({decl(std::move(key), ParameterKind::Flag, "", {}, std::move(description), false),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, false});
    return *this;
  }
  template <class F>
  Parameters& vector(std::string key, F f, std::string unit, std::string description, bool required = false) {
    entries_.push_back({decl(std::move(key), ParameterKind::Vector, std::move(unit), {}, std::move(description), required),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, false});
    return *this;
  }
  template <class F>
  Parameters& text(std::string key, F f, std::string description, bool required = false) {
    entries_.push_back({decl(std::move(key), ParameterKind::Text, "", {}, std::move(description), required),
                        [f](S& s) -> void* { return &f(s); }, nullptr, nullptr, false});
    return *this;
  }
  // f: S& -> E& for an enum E whose values 0, 1, ... are named by `names`, in order.
  template <class F>
  Parameters& choice(std::string key, F f, std::vector<std::string> names, std::string description) {
    using E = std::remove_reference_t<decltype(f(std::declval<S&>()))>;
    Entry e{decl(std::move(key), ParameterKind::Choice, "", {}, std::move(description), false),
            [f](S& s) -> void* { return &f(s); },
            [](const void* p) { return static_cast<int>(*static_cast<const E*>(p)); },
            [](void* p, int v) { *static_cast<E*>(p) = static_cast<E>(v); }, false};
    e.declaration.choices = std::move(names);
    entries_.push_back(std::move(e));
    return *this;
  }

  const std::vector<Entry>& entries() const { return entries_; }
  const Entry* find(const std::string& key) const {
    for (const auto& e : entries_)
      if (e.declaration.key == key) return &e;
    return nullptr;
  }

  // Throws InputError(file, prefix + key) for a value outside its range (and a NaN or
  // infinite one), a choice out of its names.
  void validate(const S& s, const std::string& prefix, const std::string& file = "") const {
    S& m = const_cast<S&>(s);  // read only: the accessors are shared with the reader
    for (const auto& e : entries_) {
      const ParameterDeclaration& d = e.declaration;
      void* p = e.field(m);
      const std::string key = prefix.empty() ? d.key : prefix + "." + d.key;
      if (d.kind == ParameterKind::Real) {
        const std::optional<double> v =
            e.optional_real ? *static_cast<std::optional<double>*>(p) : std::optional<double>(*static_cast<double*>(p));
        if (v && !d.range.contains(*v)) fail(file, key, d, *v);
      } else if (d.kind == ParameterKind::Integer) {
        const int v = *static_cast<int*>(p);
        if (!d.range.contains(v)) fail(file, key, d, v);
      } else if (d.kind == ParameterKind::Vector) {
        if (!static_cast<Vec3*>(p)->allFinite()) throw InputError(file, key, "must be finite");
      } else if (d.kind == ParameterKind::Choice) {
        const int v = e.as_int(p);
        if (v < 0 || v >= static_cast<int>(d.choices.size())) throw InputError(file, key, "not one of its choices");
      }
    }
  }

  // The declarations with their defaults as `defaults` holds them (docs, calibrate).
  std::vector<ParameterDeclaration> declarations(const S& defaults = S{}) const {
    S m = defaults;
    std::vector<ParameterDeclaration> out;
    for (const auto& e : entries_) {
      ParameterDeclaration d = e.declaration;
      void* p = e.field(m);
      if (!d.required) d.default_text = defaultText(e, p);
      out.push_back(std::move(d));
    }
    return out;
  }

 private:
  static ParameterDeclaration decl(std::string key, ParameterKind kind, std::string unit, Range range,
                                   std::string description, bool required) {
    ParameterDeclaration d;
    d.key = std::move(key);
    d.kind = kind;
    d.unit = std::move(unit);
    d.range = range;
    d.required = required;
    d.description = std::move(description);
    return d;
  }
  [[noreturn]] static void fail(const std::string& file, const std::string& key, const ParameterDeclaration& d,
                                double v) {
    throw InputError(file, key, "must be " + d.range.text() + (d.unit.empty() ? "" : " [" + d.unit + "]") +
                                    ", got " + Range::number(v));
  }
  static std::string defaultText(const Entry& e, void* p) {
    switch (e.declaration.kind) {
      case ParameterKind::Real:
        if (e.optional_real) {
          const auto& o = *static_cast<std::optional<double>*>(p);
          return o ? Range::number(*o) : "";
        }
        return Range::number(*static_cast<double*>(p));
      case ParameterKind::Integer:
        return std::to_string(*static_cast<int*>(p));
      case ParameterKind::Flag:
        return *static_cast<bool*>(p) ? "true" : "false";
      case ParameterKind::Vector: {
        const Vec3& v = *static_cast<Vec3*>(p);
        return "[" + Range::number(v[0]) + ", " + Range::number(v[1]) + ", " + Range::number(v[2]) + "]";
      }
      case ParameterKind::Choice: {
        const int i = e.as_int(p);
        return i >= 0 && i < static_cast<int>(e.declaration.choices.size()) ? e.declaration.choices[i] : "";
      }
      case ParameterKind::Text:
        return *static_cast<std::string*>(p);
    }
    return "";
  }
  std::vector<Entry> entries_;
};

}  // namespace needle_sim
