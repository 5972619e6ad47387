// Session manifest (session.yaml) and Session folder behaviour.
#include "capture/session.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <regex>

#include "core/error.h"
#include "core/io.h"
#include "test_util.h"

namespace station {
namespace {

using test::TempDir;

bool same_bits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

bool same_bits(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b) {
  for (int i = 0; i < 16; ++i)
    if (!same_bits(a.data()[i], b.data()[i])) return false;
  return true;
}

// A rigid pose whose entries have long binary expansions.
Eigen::Matrix4d awkward_pose(double angle, const Vec3d& axis, const Vec3d& t) {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix();
  m.topRightCorner<3, 1>() = t;
  return m;
}

SessionManifest full_manifest() {
  SessionManifest m;
  m.scanner = "sim:synthetic?mesh=data/bunny.ply&noise=0.001";
  m.turntable = "sim:turntable";
  m.intrinsics = Intrinsics{640, 480, 514.6, 514.60000000000002, 319.5, 1.0 / 3.0};
  m.axis = TurntableAxis{Vec3d(0.1, 0.2, 0.7000000000000001), Vec3d(0, -1, 0)};
  m.units = "mm";
  m.planned_views = 12;
  m.start_deg = 0.1;
  m.step_deg = 30;
  m.created = "2026-11-22T02:00:00Z";

  ViewRecord a;
  a.file = "view_000.ply";
  a.angle_deg = 0.0;
  a.initial_pose = awkward_pose(0.1, Vec3d(1, 2, 3), Vec3d(1e-300, -0.0, 1.0 / 7.0));
  // (The largest translation a manifest holds is 1e9: beyond it a corrupt file or wrong units.)
  a.reference_pose = awkward_pose(M_PI / 3, Vec3d(0, 1, 0), Vec3d(5e-324, 9.876543210987654e8, -2.5));
  a.colour_image = "view_000.png";
  a.timestamp = 1763776800.25;
  a.points = 30512;
  m.views.push_back(a);

  ViewRecord b;  // off-turntable view: only the file
  b.file = "sub dir/extra view.ply";
  m.views.push_back(b);

  ViewRecord c;
  c.file = "null";  // would be a YAML null if written unquoted
  c.angle_deg = -29.999999999999996;
  c.initial_pose = pose_from_tq(Vec3d(0.1, 0.2, 0.3), Eigen::Vector4d(0.1, -0.2, 0.3, 0.9));
  m.views.push_back(c);
  return m;
}

void expect_same(const SessionManifest& a, const SessionManifest& b) {
  EXPECT_EQ(a.version, b.version);
  EXPECT_EQ(a.scanner, b.scanner);
  EXPECT_EQ(a.turntable, b.turntable);
  ASSERT_EQ(a.intrinsics.has_value(), b.intrinsics.has_value());
  if (a.intrinsics) {
    EXPECT_EQ(a.intrinsics->width, b.intrinsics->width);
    EXPECT_EQ(a.intrinsics->height, b.intrinsics->height);
    EXPECT_TRUE(same_bits(a.intrinsics->fx, b.intrinsics->fx));
    EXPECT_TRUE(same_bits(a.intrinsics->fy, b.intrinsics->fy));
    EXPECT_TRUE(same_bits(a.intrinsics->cx, b.intrinsics->cx));
    EXPECT_TRUE(same_bits(a.intrinsics->cy, b.intrinsics->cy));
  }
  ASSERT_EQ(a.axis.has_value(), b.axis.has_value());
  if (a.axis) {
    for (int i = 0; i < 3; ++i) {
      EXPECT_TRUE(same_bits(a.axis->point[i], b.axis->point[i]));
      EXPECT_TRUE(same_bits(a.axis->direction[i], b.axis->direction[i]));
    }
  }
  EXPECT_EQ(a.units, b.units);
  EXPECT_EQ(a.planned_views, b.planned_views);
  EXPECT_TRUE(same_bits(a.start_deg, b.start_deg));
  EXPECT_TRUE(same_bits(a.step_deg, b.step_deg));
  EXPECT_EQ(a.created, b.created);
  ASSERT_EQ(a.views.size(), b.views.size());
  for (std::size_t i = 0; i < a.views.size(); ++i) {
    SCOPED_TRACE("view " + std::to_string(i));
    const ViewRecord& x = a.views[i];
    const ViewRecord& y = b.views[i];
    EXPECT_EQ(x.file, y.file);
    ASSERT_EQ(x.angle_deg.has_value(), y.angle_deg.has_value());
    if (x.angle_deg) {
      EXPECT_TRUE(same_bits(*x.angle_deg, *y.angle_deg));
    }
    ASSERT_EQ(x.initial_pose.has_value(), y.initial_pose.has_value());
    if (x.initial_pose) {
      EXPECT_TRUE(same_bits(*x.initial_pose, *y.initial_pose));
    }
    ASSERT_EQ(x.reference_pose.has_value(), y.reference_pose.has_value());
    if (x.reference_pose) {
      EXPECT_TRUE(same_bits(*x.reference_pose, *y.reference_pose));
    }
    EXPECT_EQ(x.colour_image, y.colour_image);
    ASSERT_EQ(x.timestamp.has_value(), y.timestamp.has_value());
    if (x.timestamp) {
      EXPECT_TRUE(same_bits(*x.timestamp, *y.timestamp));
    }
    EXPECT_EQ(x.points, y.points);
  }
}

// A valid manifest in hand-written style, edited by the validation tests.
const char* const kValid = R"(format: station-session
version: 1
created: 2026-11-22T02:00:00Z
scanner: "sim:synthetic?mesh=bunny.ply"
turntable: "sim:turntable"
units: m
intrinsics: {width: 640, height: 480, fx: 514.6, fy: 514.6, cx: 319.5, cy: 239.5}
turntable_axis: {point: [0, 0.1, 0.6], direction: [0, -1, 0]}
plan: {views: 12, start_deg: 0, step_deg: 30}
views:
  - file: view_000.ply
    angle_deg: 0.0
    initial_pose: {matrix: [1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]}
    reference_pose: {translation: [0.1, 0.2, 0.3], quaternion: [0, 0, 0, 1]}
    color_image: view_000.png
    timestamp: 1763776800.25
    points: 30512
  - file: view_001.ply
    angle_deg: 30
)";

std::string replaced(std::string text, const std::string& from, const std::string& to) {
  const auto pos = text.find(from);
  EXPECT_NE(pos, std::string::npos) << "test bug: '" << from << "' not in the text";
  if (pos != std::string::npos) text.replace(pos, from.size(), to);
  return text;
}

// Expects FormatError whose message starts "test.yaml: " and contains `expected`.
void expect_format_error(const std::string& text, const std::string& expected) {
  try {
    manifest_from_yaml(text, "test.yaml");
    ADD_FAILURE() << "no error; expected \"" << expected << "\" for:\n" << text;
  } catch (const FormatError& e) {
    const std::string msg = e.what();
    EXPECT_EQ(msg.rfind("test.yaml: ", 0), 0u) << msg;
    EXPECT_NE(msg.find(expected), std::string::npos)
        << "message: " << msg << "\nexpected to contain: " << expected;
  } catch (const std::exception& e) {
    ADD_FAILURE() << "wrong exception type: " << e.what();
  }
}

Cloud small_cloud(int n, float offset) {
  Cloud c;
  for (int i = 0; i < n; ++i) {
    c.points.push_back(Vec3f(offset + 0.001f * i, -0.5f * i, 1.0f / (i + 1)));
    c.normals.push_back(Vec3f(0, 0, 1));
    c.colours.push_back(Rgb{std::uint8_t(i), std::uint8_t(2 * i), 200});
  }
  return c;
}

void write_text(const fs::path& path, const std::string& text) {
  std::ofstream(path, std::ios::binary) << text;
}

// ---- round trip ---------------------------------------------------------------------

TEST(ManifestRoundTrip, EveryFieldExact) {
  const SessionManifest m = full_manifest();
  const std::string text = manifest_to_yaml(m);
  expect_same(m, manifest_from_yaml(text, "rt.yaml"));
  // Writing what was read gives the same text (stable output).
  EXPECT_EQ(manifest_to_yaml(manifest_from_yaml(text, "rt.yaml")), text);
}

TEST(ManifestRoundTrip, MinimalManifest) {
  SessionManifest m;
  m.created = "x";
  const std::string text = manifest_to_yaml(m);
  EXPECT_NE(text.find("views: []"), std::string::npos) << text;
  const SessionManifest back = manifest_from_yaml(text, "rt.yaml");
  expect_same(m, back);
  EXPECT_FALSE(back.intrinsics);
  EXPECT_FALSE(back.axis);
}

TEST(ManifestRoundTrip, ThroughFiles) {
  TempDir dir;
  SessionManifest m = full_manifest();
  fs::create_directories(dir.path() / "sub dir");
  for (const ViewRecord& v : m.views) write_text(dir.path() / v.file, "placeholder");
  write_manifest(dir.path(), m);
  expect_same(m, read_manifest(dir.path()));
  expect_same(m, read_manifest(dir.path() / kManifestName));
}

TEST(ManifestRoundTrip, HandWrittenExample) {
  const SessionManifest m = manifest_from_yaml(kValid, "test.yaml");
  EXPECT_EQ(m.scanner, "sim:synthetic?mesh=bunny.ply");
  EXPECT_EQ(m.turntable, "sim:turntable");
  EXPECT_EQ(m.created, "2026-11-22T02:00:00Z");
  EXPECT_EQ(m.units, "m");
  ASSERT_TRUE(m.intrinsics);
  EXPECT_EQ(m.intrinsics->width, 640);
  EXPECT_EQ(m.intrinsics->fx, 514.6);
  EXPECT_EQ(m.intrinsics->cy, 239.5);
  ASSERT_TRUE(m.axis);
  EXPECT_EQ(m.axis->point, Vec3d(0, 0.1, 0.6));
  EXPECT_EQ(m.axis->direction, Vec3d(0, -1, 0));
  EXPECT_EQ(m.planned_views, 12);
  EXPECT_EQ(m.step_deg, 30);
  ASSERT_EQ(m.views.size(), 2u);
  EXPECT_EQ(m.views[0].file, "view_000.ply");
  EXPECT_EQ(*m.views[0].angle_deg, 0.0);
  EXPECT_EQ(*m.views[0].initial_pose, Eigen::Matrix4d::Identity());
  Eigen::Matrix4d ref = Eigen::Matrix4d::Identity();
  ref.topRightCorner<3, 1>() = Vec3d(0.1, 0.2, 0.3);
  EXPECT_EQ(*m.views[0].reference_pose, ref);
  EXPECT_EQ(m.views[0].colour_image, "view_000.png");
  EXPECT_EQ(*m.views[0].timestamp, 1763776800.25);
  EXPECT_EQ(m.views[0].points, 30512u);
  EXPECT_EQ(m.views[1].file, "view_001.ply");
  EXPECT_EQ(*m.views[1].angle_deg, 30.0);
  EXPECT_FALSE(m.views[1].initial_pose);
  EXPECT_FALSE(m.views[1].timestamp);
  EXPECT_EQ(m.views[1].points, 0u);
}

TEST(ManifestRoundTrip, QuaternionFormIsNormalisedAndXyzw) {
  // [0, 0, 2, 2] is 90 degrees about +z, not yet unit length.
  const std::string text = replaced(kValid, "quaternion: [0, 0, 0, 1]", "quaternion: [0, 0, 2, 2]");
  const Eigen::Matrix4d p = *manifest_from_yaml(text, "test.yaml").views[0].reference_pose;
  Eigen::Matrix4d expected = Eigen::Matrix4d::Identity();
  expected.topLeftCorner<3, 3>() << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  expected.topRightCorner<3, 1>() = Vec3d(0.1, 0.2, 0.3);
  EXPECT_TRUE(p.isApprox(expected, 1e-15)) << p;
  EXPECT_TRUE(same_bits(p, pose_from_tq(Vec3d(0.1, 0.2, 0.3), Eigen::Vector4d(0, 0, 2, 2))));
}

TEST(ManifestRoundTrip, MatrixIsRowMajor) {
  const std::string text = replaced(kValid, "[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,",
                                    "[0, -1, 0, 0.5,  1, 0, 0, 0.25,  0, 0, 1, -1,");
  const Eigen::Matrix4d p = *manifest_from_yaml(text, "test.yaml").views[0].initial_pose;
  EXPECT_EQ(p(0, 1), -1);
  EXPECT_EQ(p(1, 0), 1);
  EXPECT_EQ(p(0, 3), 0.5);
  EXPECT_EQ(p(1, 3), 0.25);
  EXPECT_EQ(p(2, 3), -1);
}

TEST(ManifestRoundTrip, AxisDirectionNormalised) {
  const std::string text = replaced(kValid, "direction: [0, -1, 0]", "direction: [0, -3, 4]");
  const SessionManifest m = manifest_from_yaml(text, "test.yaml");
  EXPECT_NEAR(m.axis->direction.norm(), 1.0, 1e-15);
  EXPECT_TRUE(m.axis->direction.isApprox(Vec3d(0, -0.6, 0.8), 1e-15));
}

TEST(ManifestRoundTrip, UnknownKeysAndNullsIgnored) {
  std::string text = replaced(kValid, "units: m", "units: m\nfuture_field: {a: [1, 2]}\noperator: ~");
  text = replaced(text, "    angle_deg: 30", "    angle_deg: 30\n    exposure_us: 1200\n    timestamp:");
  // (A key given twice is an error: ManifestValidation.HeaderFields.)
  const SessionManifest m = manifest_from_yaml(text, "test.yaml");
  EXPECT_EQ(m.views.size(), 2u);
  EXPECT_FALSE(m.views[1].timestamp);  // explicit null = absent
}

TEST(ManifestRoundTrip, PlanStepDefaultsToFullTurn) {
  const std::string text = replaced(kValid, "plan: {views: 12, start_deg: 0, step_deg: 30}",
                                    "plan: {views: 8}");
  const SessionManifest m = manifest_from_yaml(text, "test.yaml");
  EXPECT_EQ(m.planned_views, 8);
  EXPECT_EQ(m.start_deg, 0);
  EXPECT_EQ(m.step_deg, 45);
}

// ---- validation ---------------------------------------------------------------------

TEST(ManifestValidation, HeaderFields) {
  expect_format_error(replaced(kValid, "format: station-session\n", ""), "format: missing");
  expect_format_error(replaced(kValid, "format: station-session", "format: other"),
                      "format: expected \"station-session\", got \"other\"");
  expect_format_error(replaced(kValid, "version: 1\n", ""), "version: missing");
  expect_format_error(replaced(kValid, "version: 1", "version: 2"), "version: unsupported version 2");
  expect_format_error(replaced(kValid, "version: 1", "version: 0"), "version: unsupported version 0");
  expect_format_error(replaced(kValid, "version: 1", "version: one"), "version: not an integer");
  expect_format_error(replaced(kValid, "version: 1", "version: 1.5"), "version: not an integer");
  expect_format_error(replaced(kValid, "units: m", "units: cm"), "units: must be \"m\" or \"mm\"");
  expect_format_error(replaced(kValid, "scanner: \"sim:synthetic?mesh=bunny.ply\"", "scanner: [a]"),
                      "scanner: not a string");
  expect_format_error(replaced(kValid, "views:\n", "viewz:\n"), "views: missing");
  expect_format_error("format: station-session\nversion: 1\nviews: {a: 1}\n", "views: not a list");
  // A key given twice would have one of its values ignored without a word.
  expect_format_error(std::string(kValid) + "units: mm\n", "test.yaml: line 20: units: given twice");
  expect_format_error(replaced(kValid, "    angle_deg: 30\n", "    angle_deg: 30\n    angle_deg: 60\n"),
                      "views[1].angle_deg: given twice");
}

TEST(ManifestValidation, Intrinsics) {
  expect_format_error(replaced(kValid, "fx: 514.6", "fx: abc"), "intrinsics.fx: not a number");
  expect_format_error(replaced(kValid, "width: 640, ", ""), "intrinsics.width: missing");
  expect_format_error(replaced(kValid, "width: 640", "width: -640"), "intrinsics.width: must be a positive");
  expect_format_error(replaced(kValid, "width: 640", "width: 640.5"), "intrinsics.width: not an integer");
  expect_format_error(replaced(kValid, "fy: 514.6", "fy: 0"), "intrinsics.fy: must be positive");
  expect_format_error(replaced(kValid, "cy: 239.5", "cy: .nan"), "intrinsics.cy: not finite");
  expect_format_error(
      replaced(kValid, "{width: 640, height: 480, fx: 514.6, fy: 514.6, cx: 319.5, cy: 239.5}", "[640, 480]"),
      "intrinsics: not a map");
}

TEST(ManifestValidation, AxisAndPlan) {
  expect_format_error(replaced(kValid, "direction: [0, -1, 0]", "direction: [0, 0, 0]"),
                      "turntable_axis.direction: zero length");
  expect_format_error(replaced(kValid, "point: [0, 0.1, 0.6]", "point: [0, 0.1]"),
                      "turntable_axis.point: has 2 entries, expected 3");
  expect_format_error(replaced(kValid, "point: [0, 0.1, 0.6]", "point: [0, x, 0.6]"),
                      "turntable_axis.point[1]: not a number");
  expect_format_error(replaced(kValid, "point: [0, 0.1, 0.6], ", ""), "turntable_axis.point: missing");
  expect_format_error(replaced(kValid, "step_deg: 30", "step_deg: -.inf"), "plan.step_deg: not finite");
  expect_format_error(replaced(kValid, "step_deg: 30", "step_deg: 1e300"),
                      "plan.step_deg: beyond +-1e6 degrees");
  expect_format_error(replaced(kValid, "views: 12", "views: -1"), "plan.views: must be a non-negative");
  // Finite but absurd (the views' own coordinates stop at 1e9): the report's errors were infinite.
  expect_format_error(replaced(kValid, "point: [0, 0.1, 0.6]", "point: [1e300, 0.1, 0.6]"),
                      "turntable_axis.point: beyond +-1e9");
}

TEST(ManifestValidation, ViewNumbers) {
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: thirty"),
                      "views[1].angle_deg: not a number");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: [30]"),
                      "views[1].angle_deg: not a number");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: .inf"),
                      "views[1].angle_deg: not finite");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: nan"),
                      "views[1].angle_deg: not finite");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: 1e999"),
                      "views[1].angle_deg: number out of range");
  // Finite, but no turntable reports it (1e308 deg became inf in radians: NaN poses).
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: 1e308"),
                      "views[1].angle_deg: beyond +-1e6 degrees");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: -2e6"),
                      "views[1].angle_deg: beyond +-1e6 degrees");
  EXPECT_EQ(*manifest_from_yaml(replaced(kValid, "angle_deg: 30", "angle_deg: 7230"), "t")
                 .views[1]
                 .angle_deg,
            7230.0);  // many turns are fine
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: 30deg"),
                      "views[1].angle_deg: not a number");
  expect_format_error(replaced(kValid, "angle_deg: 30", "angle_deg: +-30"),
                      "views[1].angle_deg: not a number");
  expect_format_error(replaced(kValid, "timestamp: 1763776800.25", "timestamp: yesterday"),
                      "views[0].timestamp: not a number");
  expect_format_error(replaced(kValid, "points: 30512", "points: -1"), "views[0].points: must not be negative");
  expect_format_error(replaced(kValid, "points: 30512", "points: 1.5"), "views[0].points: not an integer");
  expect_format_error(replaced(kValid, "points: 30512", "points: 99999999999999999999999"),
                      "views[0].points: not an integer");
  // A leading '+' is valid YAML.
  EXPECT_EQ(*manifest_from_yaml(replaced(kValid, "angle_deg: 30", "angle_deg: +30"), "t").views[1].angle_deg,
            30.0);
}

TEST(ManifestValidation, ViewFiles) {
  expect_format_error(replaced(kValid, "  - file: view_001.ply\n    angle_deg: 30", "  - angle_deg: 30"),
                      "views[1].file: missing");
  expect_format_error(replaced(kValid, "  - file: view_001.ply\n    angle_deg: 30", "  - 42"),
                      "views[1]: not a map");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: /etc/passwd"),
                      "views[1].file: absolute path");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: ../other/view_001.ply"),
                      "views[1].file: path \"../other/view_001.ply\" leaves the session folder");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: sub/../../x.ply"),
                      "views[1].file: path \"sub/../../x.ply\" leaves the session folder");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: \"\""), "views[1].file: empty path");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: sub/"), "views[1].file: path \"sub/\" does not name a file");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: view_000.ply"),
                      "views[1].file: \"view_000.ply\" is also views[0].file");
  expect_format_error(replaced(kValid, "file: view_001.ply", "file: ./view_000.ply"),
                      "views[1].file: \"./view_000.ply\" is also views[0].file");
  expect_format_error(replaced(kValid, "color_image: view_000.png", "color_image: /tmp/x.png"),
                      "views[0].color_image: absolute path");
}

TEST(ManifestValidation, Poses) {
  const std::string ident = "[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]";
  auto with_matrix = [&](const std::string& m) { return replaced(kValid, ident, m); };
  expect_format_error(with_matrix("[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0]"),
                      "views[0].initial_pose.matrix: has 15 entries, expected 16");
  expect_format_error(with_matrix("[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, x]"),
                      "views[0].initial_pose.matrix[15]: not a number");
  expect_format_error(with_matrix("[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0.5, 0, 1]"),
                      "views[0].initial_pose.matrix: last row is not [0, 0, 0, 1]");
  expect_format_error(with_matrix("[2, 0, 0, 0,  0, 2, 0, 0,  0, 0, 2, 0,  0, 0, 0, 1]"),
                      "views[0].initial_pose.matrix: rotation is not orthonormal");
  expect_format_error(with_matrix("[1, 0, 0, 0,  0, 1, 0.001, 0,  0, 0, 1, 0,  0, 0, 0, 1]"),
                      "views[0].initial_pose.matrix: rotation is not orthonormal");
  expect_format_error(with_matrix("[-1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]"),
                      "views[0].initial_pose.matrix: rotation is a reflection");
  expect_format_error(with_matrix("[1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, .nan]"),
                      "views[0].initial_pose.matrix[15]: not finite");
  expect_format_error(with_matrix("[1, 0, 0, 1e300,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]"),
                      "views[0].initial_pose.matrix: translation beyond +-1e9");
  // Rounded to 6 digits by another tool: within the 1e-4 tolerance.
  EXPECT_NO_THROW(manifest_from_yaml(
      with_matrix("[0.707107, -0.707107, 0, 0,  0.707107, 0.707107, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1]"),
      "t"));

  const std::string tq = "{translation: [0.1, 0.2, 0.3], quaternion: [0, 0, 0, 1]}";
  auto with_ref = [&](const std::string& p) { return replaced(kValid, tq, p); };
  expect_format_error(with_ref("{translation: [0.1, 0.2, 0.3], quaternion: [0, 0, 0, 0]}"),
                      "views[0].reference_pose.quaternion: zero length");
  expect_format_error(with_ref("{translation: [0.1, 0.2, 0.3], quaternion: [0, 0, 1]}"),
                      "views[0].reference_pose.quaternion: has 3 entries, expected 4");
  expect_format_error(with_ref("{translation: [0.1, 0.2], quaternion: [0, 0, 0, 1]}"),
                      "views[0].reference_pose.translation: has 2 entries, expected 3");
  expect_format_error(with_ref("{translation: [0.1, 0.2, 0.3]}"),
                      "views[0].reference_pose.quaternion: missing");
  expect_format_error(with_ref("{quaternion: [0, 0, 0, 1]}"), "views[0].reference_pose.translation: missing");
  expect_format_error(with_ref("{rotation: [0, 0, 0, 1]}"),
                      "views[0].reference_pose: needs matrix or translation + quaternion");
  expect_format_error(with_ref("{matrix: " + ident + ", translation: [0, 0, 0]}"),
                      "views[0].reference_pose: give either matrix or translation + quaternion");
  expect_format_error(with_ref("[1, 2, 3]"), "views[0].reference_pose: not a map");
  // Huge but finite quaternion entries normalise without overflow.
  const auto m = manifest_from_yaml(with_ref("{translation: [0, 0, 0], quaternion: [0, 0, 1e308, 1e308]}"), "t");
  EXPECT_TRUE(m.views[0].reference_pose->allFinite());
}

TEST(ManifestValidation, SyntaxErrorsNameLineAndColumn) {
  expect_format_error("format: station-session\nversion: 1\nviews: [\n", "YAML syntax error at line");
  expect_format_error("format: station-session\nversion: 1\n  bad indent: [1\n", "column");
  expect_format_error("", "empty file");
  expect_format_error("- 1\n- 2\n", "top level is not a map");
  expect_format_error("just a string", "top level is not a map");
}

TEST(ManifestValidation, FirstProblemIsReported) {
  std::string text = replaced(kValid, "angle_deg: 0.0", "angle_deg: bad0");
  text = replaced(text, "angle_deg: 30", "angle_deg: bad1");
  expect_format_error(text, "views[0].angle_deg: not a number");
}

TEST(ManifestValidation, WriterRefusesInvalidManifests) {
  SessionManifest m = full_manifest();
  m.views[0].initial_pose->coeffRef(0, 0) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
  m = full_manifest();
  m.views[1].file = "../escape.ply";
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
  m = full_manifest();
  m.views[1].file = m.views[0].file;
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
  m = full_manifest();
  m.units = "inch";
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
  m = full_manifest();
  m.axis->direction = Vec3d::Zero();
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
  m = full_manifest();
  m.views[1].angle_deg = 1e308;
  EXPECT_THROW(manifest_to_yaml(m), InvalidInput);
}

// ---- robustness (what the fuzzer checks, on a fixed budget) --------------------------

// Parses `text`; only success or FormatError are acceptable.
void expect_total(const std::string& text) {
  try {
    manifest_from_yaml(text, "fuzz.yaml");
  } catch (const FormatError&) {
  } catch (const std::exception& e) {
    ADD_FAILURE() << "non-FormatError exception: " << e.what();
  } catch (...) {
    ADD_FAILURE() << "unknown exception";
  }
}

TEST(ManifestRobustness, RandomBytes) {
  std::mt19937 rng(12345);
  for (int i = 0; i < 2000; ++i) {
    std::string s(rng() % 200, '\0');
    for (char& c : s) c = char(rng() & 0xff);
    expect_total(s);
  }
}

TEST(ManifestRobustness, MutatedManifests) {
  std::mt19937 rng(777);
  const std::string base = manifest_to_yaml(full_manifest()) + kValid;
  const std::string alphabet = "[]{}:,-?&*!|>'\"#%@` \n\t0123456789.eE+-xyzabc~";
  for (int i = 0; i < 2000; ++i) {
    std::string s = i % 2 ? base : std::string(kValid);
    const int edits = 1 + int(rng() % 4);
    for (int e = 0; e < edits; ++e) {
      const std::size_t pos = rng() % s.size();
      switch (rng() % 3) {
        case 0: s[pos] = alphabet[rng() % alphabet.size()]; break;
        case 1: s.erase(pos, 1 + rng() % 8); break;
        default: s.insert(pos, 1, alphabet[rng() % alphabet.size()]); break;
      }
      if (s.empty()) s = "x";
    }
    expect_total(s);
  }
}

TEST(ManifestRobustness, DeepNestingAndHugeValues) {
  expect_total(std::string(100000, '['));
  expect_total(std::string(100000, '{'));
  expect_total("views: " + std::string(50000, '[') + std::string(50000, ']'));
  std::string block;
  for (int i = 0; i < 20000; ++i) block += "- ";
  expect_total(block + "x\n");
  expect_total("format: station-session\nversion: 99999999999999999999999999\nviews: []\n");
  expect_total("format: station-session\nversion: -99999999999999999999999999\nviews: []\n");
  expect_total(replaced(kValid, "angle_deg: 30", "angle_deg: 1" + std::string(5000, '0')));
  expect_total(replaced(kValid, "angle_deg: 30", "angle_deg: 0." + std::string(5000, '0') + "1"));
  expect_total(replaced(kValid, "fx: 514.6", "fx: 1e-400"));
  expect_total(replaced(kValid, "file: view_001.ply", "file: " + std::string(100000, 'a')));
  // Aliases: a self-referencing list and a "billion laughs" shape.
  expect_total("format: station-session\nversion: 1\nviews: &a [*a]\n");
  expect_total("format: station-session\nversion: 1\nviews: &v\n  - file: a\n    initial_pose: *v\n");
  std::string laughs = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n";
  for (int i = 1; i < 30; ++i)
    laughs += "a" + std::to_string(i) + ": &a" + std::to_string(i) + " [*a" + std::to_string(i - 1) +
              ", *a" + std::to_string(i - 1) + ", *a" + std::to_string(i - 1) + "]\n";
  expect_total(laughs + "format: station-session\nversion: 1\nviews: *a29\n");
  expect_total(std::string("format: station-session\0version: 1", 34));
  expect_total("%YAML 9.9\n---\nformat: station-session\n");
  expect_total("--- !!binary |\n  R0lGODlhDAAMAIQAAP\n");
  expect_total("? [a, b]\n: c\nformat: station-session\nversion: 1\nviews: []\n");
}

// ---- files and sessions ---------------------------------------------------------------

TEST(ManifestRead, MissingViewFileNamed) {
  TempDir dir;
  SessionManifest m = full_manifest();
  m.views.resize(1);
  write_manifest(dir.path(), m);
  try {
    read_manifest(dir.path());
    ADD_FAILURE() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find("view_000.ply: view file missing"), std::string::npos)
        << e.what();
  }
  write_text(dir.path() / "view_000.ply", "x");
  EXPECT_NO_THROW(read_manifest(dir.path()));
}

TEST(ManifestRead, NotASessionFolder) {
  TempDir dir;
  EXPECT_THROW(read_manifest(dir.path()), IoError);
  EXPECT_THROW(read_manifest(dir.path() / "nope"), IoError);
  EXPECT_THROW(Session::open(dir.path()), IoError);
  write_text(dir.path() / kManifestName, "format: [");
  EXPECT_THROW(read_manifest(dir.path()), FormatError);
  // A view given for the session: said so (was the YAML parser's syntax error).
  write_text(dir.path() / "view_000.PLY", "ply\nformat binary_little_endian 1.0\n");
  try {
    read_manifest(dir.path() / "view_000.PLY");
    FAIL() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find("view_000.PLY: a ply file, not a session"), std::string::npos) << e.what();
  }
}

TEST(Session, CreateWritesEmptyManifest) {
  TempDir dir;
  SessionManifest m;
  m.scanner = "sim:synthetic";
  const Session s = Session::create(dir.path() / "a" / "b", m);
  EXPECT_EQ(s.dir(), dir.path() / "a" / "b");
  EXPECT_TRUE(fs::exists(dir.path() / "a" / "b" / kManifestName));
  EXPECT_TRUE(std::regex_match(s.manifest().created,
                               std::regex(R"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ)")))
      << s.manifest().created;
  const Session back = Session::open(dir.path() / "a" / "b");
  EXPECT_EQ(back.manifest().scanner, "sim:synthetic");
  EXPECT_EQ(back.manifest().created, s.manifest().created);
  EXPECT_TRUE(back.manifest().views.empty());
}

TEST(Session, CreateRefusesExistingSession) {
  TempDir dir;
  Session::create(dir.path(), {});
  const std::string before = read_file_bytes(dir.path() / kManifestName);
  try {
    Session::create(dir.path(), {});
    ADD_FAILURE() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find("already holds a session; use --resume"), std::string::npos)
        << e.what();
  }
  EXPECT_EQ(read_file_bytes(dir.path() / kManifestName), before);
}

TEST(Session, CreateFailsWhereNoFolderCanBe) {
  TempDir dir;
  write_text(dir.path() / "file", "x");
  EXPECT_THROW(Session::create(dir.path() / "file", {}), IoError);
  EXPECT_THROW(Session::create(dir.path() / "file" / "sub", {}), IoError);
}

TEST(Session, AddViewAndReopen) {
  TempDir dir;
  SessionManifest m;
  m.scanner = "sim:synthetic";
  m.planned_views = 3;
  m.step_deg = 120;
  Session s = Session::create(dir.path(), m);

  // 2x1 colour image: red, then blue.
  const std::vector<std::uint8_t> rgb = {255, 0, 0, 0, 0, 255};
  std::vector<Cloud> clouds;
  for (int i = 0; i < 3; ++i) {
    clouds.push_back(small_cloud(10 + i, float(i)));
    ViewRecord r;
    r.angle_deg = 120.0 * i;
    r.initial_pose = awkward_pose(0.3 * i, Vec3d(0, 1, 0), Vec3d(0.1, 0, 0));
    r.timestamp = 1763776800.0 + i;
    const std::size_t idx = i == 1 ? s.add_view(clouds.back(), r, rgb, 2, 1) : s.add_view(clouds.back(), r);
    EXPECT_EQ(idx, std::size_t(i));
  }
  EXPECT_EQ(s.manifest().views[1].colour_image, "view_001.png");
  EXPECT_TRUE(s.manifest().views[0].colour_image.empty());

  const Session back = Session::open(dir.path());
  expect_same(s.manifest(), back.manifest());
  ASSERT_EQ(back.manifest().views.size(), 3u);
  for (int i = 0; i < 3; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "view_%03d.ply", i);
    EXPECT_EQ(back.manifest().views[i].file, name);
    EXPECT_EQ(back.manifest().views[i].points, clouds[i].size());
    const Cloud c = back.load_view(i);
    ASSERT_EQ(c.size(), clouds[i].size());
    for (std::size_t k = 0; k < c.size(); ++k) EXPECT_EQ(c.points[k], clouds[i].points[k]);
  }
  const std::string png = read_file_bytes(dir.path() / "view_001.png");
  const cv::Mat img = cv::imdecode(std::vector<std::uint8_t>(png.begin(), png.end()), cv::IMREAD_COLOR);
  ASSERT_EQ(img.cols, 2);
  ASSERT_EQ(img.rows, 1);
  EXPECT_EQ(img.at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 255));  // BGR red
  EXPECT_EQ(img.at<cv::Vec3b>(0, 1), cv::Vec3b(255, 0, 0));  // BGR blue
  EXPECT_THROW(back.load_view(3), InvalidInput);
}

TEST(Session, LeftoverOfCrashIsIgnoredThenOverwritten) {
  TempDir dir;
  Session s = Session::create(dir.path(), {});
  s.add_view(small_cloud(5, 0), {});
  s.add_view(small_cloud(5, 1), {});
  // A crash between writing view 2 and committing it to the manifest leaves a
  // file the manifest does not list, plus possibly a stray temporary.
  write_text(dir.path() / "view_002.ply", "ply\ngarbage from an interrupted write");
  write_text(dir.path() / "view_002.ply.tmp-4242-0", "half");
  write_text(dir.path() / (std::string(kManifestName) + ".tmp-4242-1"), "format: [");

  Session resumed = Session::open(dir.path());
  ASSERT_EQ(resumed.manifest().views.size(), 2u);
  const Cloud c = small_cloud(7, 2);
  EXPECT_EQ(resumed.add_view(c, {}), 2u);
  EXPECT_EQ(resumed.manifest().views[2].file, "view_002.ply");
  const Cloud back = Session::open(dir.path()).load_view(2);
  ASSERT_EQ(back.size(), 7u);
  EXPECT_EQ(back.points[6], c.points[6]);
}

TEST(Session, AddViewNeverOverwritesCommittedFiles) {
  TempDir dir;
  // An imported manifest that already uses view_001.ply for its first view.
  write_text(dir.path() / "view_001.ply", "committed");
  SessionManifest m;
  m.scanner = "import";
  m.views.push_back(ViewRecord{});
  m.views[0].file = "view_001.ply";
  write_manifest(dir.path(), m);
  Session s = Session::open(dir.path());
  EXPECT_EQ(s.add_view(small_cloud(3, 0), {}), 1u);
  EXPECT_EQ(s.manifest().views[1].file, "view_002.ply");
  EXPECT_EQ(read_file_bytes(dir.path() / "view_001.ply"), "committed");
}

TEST(Session, AddViewRejectsBadInputWithoutChanges) {
  TempDir dir;
  Session s = Session::create(dir.path(), {});
  const std::string before = read_file_bytes(dir.path() / kManifestName);
  EXPECT_THROW(s.add_view(small_cloud(3, 0), {}, {1, 2, 3}, 2, 1), InvalidInput);
  ViewRecord bad;
  bad.angle_deg = std::numeric_limits<double>::infinity();
  EXPECT_THROW(s.add_view(small_cloud(3, 0), bad), InvalidInput);
  bad = {};
  bad.initial_pose = 2.0 * Eigen::Matrix4d::Identity();
  EXPECT_THROW(s.add_view(small_cloud(3, 0), bad), InvalidInput);
  EXPECT_TRUE(s.manifest().views.empty());
  EXPECT_EQ(read_file_bytes(dir.path() / kManifestName), before);
}

TEST(SessionPose, FromTranslationQuaternion) {
  EXPECT_EQ(pose_from_tq(Vec3d::Zero(), Eigen::Vector4d(0, 0, 0, 1)), Eigen::Matrix4d::Identity());
  const Eigen::Matrix4d p = pose_from_tq(Vec3d(1, 2, 3), Eigen::Vector4d(1, 0, 0, 1));  // 90 deg about x
  const Vec3d y = (p * Eigen::Vector4d(0, 1, 0, 1)).head<3>();
  EXPECT_TRUE(y.isApprox(Vec3d(1, 2, 4), 1e-15)) << y.transpose();
  EXPECT_EQ(p.row(3), Eigen::RowVector4d(0, 0, 0, 1));
  EXPECT_THROW(pose_from_tq(Vec3d::Zero(), Eigen::Vector4d::Zero()), InvalidInput);
}

}  // namespace
}  // namespace station
