#include "core/stanford_conf.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>

#include "core/error.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "test_util.h"

namespace station {
namespace {

namespace fs = std::filesystem;

fs::path write_temp(const std::string& name, const std::string& text) {
  const fs::path p = fs::temp_directory_path() / name;
  std::ofstream(p) << text;
  return p;
}

TEST(StanfordConf, ParsesBmeshLinesAsTransposedRotationAndTranslation) {
  // 90 degrees about z: q = (0, 0, sin 45, cos 45); R maps x to y, so R^T maps y to x.
  const fs::path p = write_temp("station_conf_ok.conf",
                                "camera 0 0 0 0 0 0 1\nbmesh a.ply 1 2 3 0 0 0.70710678 0.70710678\n"
                                "mesh ignored.ply\nbmesh b.ply 0 0 0 0 0 0 1\n");
  const auto scans = read_stanford_conf(p);
  ASSERT_EQ(scans.size(), 2u);
  EXPECT_EQ(scans[0].file, "a.ply");
  EXPECT_EQ(scans[1].file, "b.ply");
  const Eigen::Vector4d y(0, 1, 0, 1);
  const Eigen::Vector4d moved = scans[0].pose * y;
  EXPECT_NEAR(moved.x(), 1 + 1, 1e-9);
  EXPECT_NEAR(moved.y(), 2 + 0, 1e-9);
  EXPECT_NEAR(moved.z(), 3, 1e-9);
  EXPECT_TRUE(scans[1].pose.isApprox(Eigen::Matrix4d::Identity()));
  fs::remove(p);
}

TEST(StanfordConf, BadLinesNameTheFileAndLine) {
  const fs::path p = write_temp("station_conf_bad.conf", "camera 0\nbmesh a.ply 1 2\n");
  try {
    read_stanford_conf(p);
    FAIL() << "no error";
  } catch (const FormatError& e) {
    EXPECT_NE(std::string(e.what()).find("station_conf_bad.conf: line 2"), std::string::npos) << e.what();
  }
  const fs::path z = write_temp("station_conf_zero.conf", "bmesh a.ply 1 2 3 0 0 0 0\n");
  EXPECT_THROW(read_stanford_conf(z), FormatError);
  const fs::path n = write_temp("station_conf_nan.conf", "bmesh a.ply nan 2 3 0 0 0 1\n");
  EXPECT_THROW(read_stanford_conf(n), FormatError);
  EXPECT_THROW(read_stanford_conf(fs::temp_directory_path() / "station_no_such.conf"), IoError);
  EXPECT_THROW(merge_stanford_scans(write_temp("station_conf_empty.conf", "camera 0\n")), FormatError);
  for (const fs::path& f : {p, z, n}) fs::remove(f);
}

// The bundled dragon: with the convention above, neighbouring scans (24 degrees
// apart) overlap closely; with R instead of R^T they would be ~40 degrees apart.
TEST(StanfordConf, DragonScansOverlapOnceMerged) {
  const fs::path conf = test::source_dir() / "data/dragon_stand/dragonStandRight.conf";
  const auto scans = read_stanford_conf(conf);
  ASSERT_EQ(scans.size(), 15u);
  auto load = [&](const StanfordScan& s) {
    Cloud c = read_cloud(conf.parent_path() / s.file);
    transform_cloud(c, s.pose);
    return c.points;
  };
  const auto a = load(scans[0]), b = load(scans[1]);
  const PointIndex index(a);
  std::vector<float> d;
  for (const Vec3f& p : b) d.push_back(index.nearest(p).second);
  std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
  const float median = d[d.size() / 2];
  EXPECT_LT(median, 0.0015f);  // the bundled scans' spacing is about 1 mm
  const Cloud merged = merge_stanford_scans(conf, 2);
  std::size_t expected = 0;
  for (const auto& s : scans) expected += (read_cloud(conf.parent_path() / s.file).size() + 1) / 2;
  EXPECT_EQ(merged.size(), expected);
  EXPECT_THROW(merge_stanford_scans(conf, 0), InvalidInput);
}

}  // namespace
}  // namespace station
