#pragma once
// Stanford 3D Scanning Repository alignment files (".conf"), as shipped with the
// dragon turntable scans (data/dragon_stand/, ../shared/data/stanford_dragon_stand/).
//
// Lines "bmesh FILE tx ty tz qx qy qz qw" give each scan's pose; the convention that
// aligns the scans is p_world = R^T p_scan + t, R the rotation of the unit
// quaternion (checked numerically on the dragon; docs/session-format.md). Other
// lines (camera, mesh) are ignored.
#include <filesystem>
#include <string>
#include <vector>

#include "core/geometry.h"

namespace station {

struct StanfordScan {
  std::string file;    ///< as written in the .conf (relative to its folder)
  Eigen::Matrix4d pose;  ///< scan -> world: [R^T | t]
};

/// The bmesh entries in file order. FormatError naming the file and line for a
/// malformed bmesh line, a non-finite number or a zero quaternion; IoError when
/// the file cannot be read.
std::vector<StanfordScan> read_stanford_conf(const std::filesystem::path& conf);

/// Every scan of the .conf read (read_cloud, relative to the .conf's folder), every
/// `every`-th point kept, transformed by its pose and concatenated (normals and
/// colours dropped unless every scan has them).
Cloud merge_stanford_scans(const std::filesystem::path& conf, int every = 1);

}  // namespace station
