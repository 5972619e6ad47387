#pragma once
// Private to bench/: the Stanford dragon turntable session, from ../shared/data
// (full scans) or the bundled copy, as `station import --stanford-conf` makes it.
#include <string>
#include <vector>

#include "capture/session.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "harness.h"

namespace station::bench {

struct DragonSession {
  std::vector<Cloud> clouds;
  SessionManifest manifest;
  std::string where;
};

/// Angles 0, 24, ... and reference poses [R^T | t] (docs/session-format.md), no axis.
inline DragonSession load_dragon(const Options& options) {
  DragonSession s;
  fs::path dir = options.shared_dir / "stanford_dragon_stand";
  s.where = "../shared/data/stanford_dragon_stand (full scans)";
  if (!options.use_shared || !fs::exists(dir / "dragonStandRight.conf")) {
    dir = options.source_dir / "data" / "dragon_stand";
    s.where = "data/dragon_stand (bundled: every 5th point; ../shared missing)";
  }
  s.manifest.scanner = "import";
  for (const StanfordScan& scan : read_stanford_conf(dir / "dragonStandRight.conf")) {
    ViewRecord v;
    v.file = scan.file;
    v.angle_deg = std::stoi(scan.file.substr(scan.file.rfind('_') + 1));
    v.reference_pose = scan.pose;
    s.manifest.views.push_back(v);
    s.clouds.push_back(read_cloud(dir / scan.file));
  }
  return s;
}

}  // namespace station::bench
