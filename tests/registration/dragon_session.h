#pragma once
// The bundled dragon turntable session for the registration tests, as
// `station import --stanford-conf` makes it: angles 0, 24, ... and reference
// poses [R^T | t] (docs/session-format.md), no axis.
#include <string>
#include <vector>

#include "capture/session.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "test_util.h"

namespace station::test {

inline SessionManifest dragon_session(std::vector<Cloud>& clouds) {
  const auto dir = source_dir() / "data/dragon_stand";
  SessionManifest m;
  m.scanner = "import";
  for (const StanfordScan& scan : read_stanford_conf(dir / "dragonStandRight.conf")) {
    ViewRecord v;
    v.file = scan.file;
    v.angle_deg = std::stoi(scan.file.substr(scan.file.rfind('_') + 1));
    v.reference_pose = scan.pose;
    m.views.push_back(v);
    clouds.push_back(read_cloud(dir / scan.file));
  }
  return m;
}

}  // namespace station::test
