#include "core/stanford_conf.h"

#include <cmath>
#include <sstream>

#include <Eigen/Geometry>

#include "core/error.h"
#include "core/io.h"

namespace station {

std::vector<StanfordScan> read_stanford_conf(const std::filesystem::path& conf) {
  std::istringstream in(read_file_bytes(conf));
  std::vector<StanfordScan> scans;
  std::string line;
  int n = 0;
  auto fail = [&](const std::string& what) {
    throw FormatError(conf.string() + ": line " + std::to_string(n) + ": " + what);
  };
  while (std::getline(in, line)) {
    ++n;
    std::istringstream ls(line);
    std::string tag, file;
    ls >> tag;
    if (tag != "bmesh") continue;
    double v[7];
    ls >> file;
    for (double& x : v) ls >> x;
    if (!ls || file.empty()) fail("expected bmesh FILE tx ty tz qx qy qz qw");
    for (double x : v)
      if (!std::isfinite(x)) fail("non-finite number");
    Eigen::Quaterniond q(v[6], v[3], v[4], v[5]);
    if (q.norm() < 1e-12) fail("zero quaternion");
    q.normalize();
    StanfordScan s;
    s.file = file;
    s.pose = Eigen::Matrix4d::Identity();
    s.pose.block<3, 3>(0, 0) = q.toRotationMatrix().transpose();
    s.pose.block<3, 1>(0, 3) = Vec3d(v[0], v[1], v[2]);
    scans.push_back(std::move(s));
  }
  return scans;
}

Cloud merge_stanford_scans(const std::filesystem::path& conf, int every) {
  if (every < 1) throw InvalidInput("merge_stanford_scans: every must be at least 1");
  const auto scans = read_stanford_conf(conf);
  if (scans.empty()) throw FormatError(conf.string() + ": no bmesh lines");
  Cloud all;
  bool normals = true, colours = true;
  for (const StanfordScan& s : scans) {
    Cloud c = read_cloud(conf.parent_path() / s.file);
    Cloud kept;
    for (std::size_t i = 0; i < c.size(); i += every) {
      kept.points.push_back(c.points[i]);
      if (c.has_normals()) kept.normals.push_back(c.normals[i]);
      if (c.has_colours()) kept.colours.push_back(c.colours[i]);
    }
    transform_cloud(kept, s.pose);
    normals = normals && kept.has_normals();
    colours = colours && kept.has_colours();
    all.points.insert(all.points.end(), kept.points.begin(), kept.points.end());
    all.normals.insert(all.normals.end(), kept.normals.begin(), kept.normals.end());
    all.colours.insert(all.colours.end(), kept.colours.begin(), kept.colours.end());
  }
  if (!normals) all.normals.clear();
  if (!colours) all.colours.clear();
  return all;
}

}  // namespace station
