#include "needle_sim/core/parameters.hpp"

namespace needle_sim {

std::string Range::number(double v) {
  if (std::isinf(v)) return v > 0 ? "inf" : "-inf";
  char b[32];
  std::snprintf(b, sizeof b, "%g", v);
  std::string s = b;  // 1e+06 -> 1e6, 1e-08 -> 1e-8
  for (const char* from : {"e+0", "e+", "e-0"}) {
    const size_t at = s.find(from);
    if (at != std::string::npos) s.replace(at, std::string(from).size(), from[1] == '-' ? "e-" : "e");
  }
  return s;
}

std::string Range::text() const {
  const bool lo_inf = std::isinf(lo), hi_inf = std::isinf(hi);
  if (lo_inf && hi_inf) return "finite";
  if (hi_inf) return std::string(lo_closed ? ">= " : "> ") + number(lo);
  if (lo_inf) return std::string(hi_closed ? "<= " : "< ") + number(hi);
  return std::string("in ") + (lo_closed ? "[" : "(") + number(lo) + ", " + number(hi) + (hi_closed ? "]" : ")");
}

std::string ParameterDeclaration::type() const {
  switch (kind) {
    case ParameterKind::Real:
      return "number";
    case ParameterKind::Integer:
      return "integer";
    case ParameterKind::Flag:
      return "bool";
    case ParameterKind::Vector:
      return "[x, y, z]";
    case ParameterKind::Choice: {
      std::string s;
      for (const auto& c : choices) s += (s.empty() ? "" : " | ") + c;
      return s;
    }
    case ParameterKind::Text:
      return "string";
  }
  return "";
}

}  // namespace needle_sim
