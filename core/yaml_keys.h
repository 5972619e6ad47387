#pragma once
// A check yaml-cpp does not make: the same key twice in one mapping. yaml-cpp keeps
// both entries and answers a lookup with one of them, so the other value would be
// ignored without a word (a session.yaml with `units: m` and later `units: mm`).
// Header only; included by the .cpp files that parse YAML (never by a widely
// included header).
#include <yaml-cpp/yaml.h>

#include <set>
#include <string>

namespace station {

struct DuplicateYamlKey {
  std::string path;  ///< dotted path of the second occurrence ("views[3].angle_deg"); empty: none
  int line = 0;      ///< its 1-based line, 0 when unknown
};

namespace yaml_keys_detail {
/// Walks at most `budget` nodes and 16 levels: an alias may point back at its own
/// parent (`views: &a [*a]`) or nest a "billion laughs"; past either limit the rest
/// is left to the reader's own checks.
inline DuplicateYamlKey walk(const YAML::Node& n, const std::string& at, int depth, long& budget) {
  if (depth > 16 || --budget < 0) return {};
  if (n.IsMap()) {
    std::set<std::string> seen;
    for (const auto& kv : n) {
      const std::string k = kv.first.IsScalar() ? kv.first.Scalar() : std::string("?");
      const std::string path = at.empty() ? k : at + "." + k;
      if (!seen.insert(k).second) return {path, kv.first.Mark().is_null() ? 0 : kv.first.Mark().line + 1};
      if (DuplicateYamlKey d = walk(kv.second, path, depth + 1, budget); !d.path.empty()) return d;
      if (budget < 0) return {};
    }
  } else if (n.IsSequence()) {
    for (std::size_t i = 0; i < n.size() && budget >= 0; ++i)
      if (DuplicateYamlKey d = walk(n[i], at + "[" + std::to_string(i) + "]", depth + 1, budget); !d.path.empty())
        return d;
  }
  return {};
}
}  // namespace yaml_keys_detail

/// The first key given twice in one mapping under n (within the first million nodes).
inline DuplicateYamlKey duplicate_yaml_key(const YAML::Node& n) {
  long budget = 1000000;
  return yaml_keys_detail::walk(n, "", 0, budget);
}

/// The one-line complaint for d in file `name` (empty when d is none).
inline std::string duplicate_yaml_key_message(const DuplicateYamlKey& d, const std::string& name) {
  if (d.path.empty()) return {};
  return name + ": " + (d.line > 0 ? "line " + std::to_string(d.line) + ": " : std::string()) + d.path +
         ": given twice (one of the two values would be ignored)";
}

}  // namespace station
