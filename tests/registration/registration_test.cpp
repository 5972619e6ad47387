// Registration of a session (capture/registration.h): the bundled dragon and
// bad input. ICP, pose graph and axis pieces have their own test files.
#include "registration/registration.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <fstream>
#include <random>
#include <set>
#include <sstream>

#include "core/error.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "dragon_session.h"
#include "test_util.h"

namespace station {
namespace {

SessionManifest dragon_manifest(std::vector<Cloud>& clouds) { return test::dragon_session(clouds); }

TEST(Registration, DragonWithAnglesButNoAxisMatchesStanford) {
  std::vector<Cloud> clouds;
  const SessionManifest m = dragon_manifest(clouds);
  ASSERT_EQ(m.views.size(), 15u);
  const auto t0 = std::chrono::steady_clock::now();
  const RegistrationResult r = register_views(clouds, m);
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_TRUE(r.failed_views.empty());
  ASSERT_TRUE(r.axis_fit.has_value());
  EXPECT_EQ(r.views_with_reference, 15);
  for (std::size_t i = 0; i < r.views.size(); ++i)
    std::printf("view %2zu: rot %.3f deg, trans %.3f mm %s\n", i, r.views[i].rotation_error_deg.value_or(-1),
                1000 * r.views[i].translation_error.value_or(-1), r.views[i].message.c_str());
  std::printf("max %.3f deg / %.3f mm, median %.3f deg / %.3f mm, %.2f s (prep %.2f init %.2f refine %.2f merge %.2f)\n",
              r.max_rotation_error_deg, 1000 * r.max_translation_error, r.median_rotation_error_deg,
              1000 * r.median_translation_error, secs, r.seconds_prepare, r.seconds_initial,
              r.seconds_refine, r.seconds_merge);
  RecordProperty("max_rotation_error_deg", std::to_string(r.max_rotation_error_deg));
  RecordProperty("median_rotation_error_deg", std::to_string(r.median_rotation_error_deg));
  RecordProperty("max_translation_error_m", std::to_string(r.max_translation_error));
  // The target is 0.5 deg / 1 mm for every view and a 0.25 deg median.
  // Reached with the rigid turntable (docs/registration.md): 0.32 deg / 2.0 mm
  // max, 0.19 deg / 1.5 mm median (free poses: 0.60 deg / 2.6 mm, 0.27 deg):
  // the rotation targets are met, the translation one is not; what is left is
  // a 1 mm shift in depth of the turntable axis against the axis of Stanford's
  // poses, consistent over all pairs. Asserted: the rotation targets, and the
  // translation we reach with a small margin, so a regression fails.
  EXPECT_TRUE(r.rigid_turntable);
  EXPECT_LT(r.rigid_deviation_deg, 0.5);
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.median_rotation_error_deg, 0.25);
  EXPECT_LT(r.max_translation_error, 0.0023);
  EXPECT_LT(r.median_translation_error, 0.0017);
  // Every pair of the last round converged, and the axis found is vertical
  // in the scanner frame (the Cyberware's turntable turns about y).
  for (const PairDiagnostics& p : r.pairs) {
    if (p.round == 2) {
      EXPECT_TRUE(p.converged) << p.from << "-" << p.to << ": " << p.message;
    }
  }
  EXPECT_GT(std::abs(r.axis->direction.normalized().y()), 0.999);
  EXPECT_FALSE(r.degenerate);
  EXPECT_GT(r.merged.size(), 50000u);
  EXPECT_TRUE(r.merged.has_normals());
  // Are Stanford's poses or ours closer to the scans? The same pairs' RMS
  // point-to-plane residual under both (docs/registration.md): ours is lower on
  // every pair, so the 0.6 deg gap is not a worse fit of the data. Refining from
  // Stanford's poses converges to ours (measured on the full scans).
  ASSERT_EQ(r.pair_residuals.size(), 30u);
  ASSERT_TRUE(r.mean_reference_pair_rmse.has_value());
  std::printf("pair residual: ours %.4f mm, Stanford's poses %.4f mm\n", 1000 * r.mean_pair_rmse,
              1000 * *r.mean_reference_pair_rmse);
  EXPECT_LT(r.mean_pair_rmse, 0.85 * *r.mean_reference_pair_rmse);
  int better = 0;
  for (const PairResidual& pr : r.pair_residuals) {
    EXPECT_GT(pr.matches, 100u) << pr.from << "-" << pr.to;
    EXPECT_GT(pr.rmse, 0.0);
    if (pr.rmse < *pr.reference_rmse) ++better;
  }
  EXPECT_GE(better, 28);
  // Started at Stanford's poses, the refinement walks back to the same optimum.
  SessionManifest from_reference = m;
  for (ViewRecord& v : from_reference.views) v.initial_pose = v.reference_pose;
  const RegistrationResult r2 = register_views(clouds, from_reference);
  ASSERT_TRUE(r2.failed_views.empty());
  for (std::size_t i = 0; i < r.poses.size(); ++i) {
    const auto [rot, trans] = relative_pose_error(r.poses[0], r.poses[i], r2.poses[0], r2.poses[i]);
    EXPECT_LT(rot, 0.05) << "view " << i;
    EXPECT_LT(trans, 2e-4) << "view " << i;
  }
}

// Bad input: an empty view, a view of NaNs and a view that overlaps nothing
// fail with messages naming them; the rest is registered, merged and written.
TEST(Registration, BadViewsFailAloneAndAreNamed) {
  std::vector<Cloud> all;
  const SessionManifest dragon = dragon_manifest(all);
  test::TempDir dir;
  SessionManifest m;
  m.scanner = "import";
  Session session = Session::create(dir / "s", m);
  for (int i = 0; i < 6; ++i) session.add_view(all[i], dragon.views[i]);
  ViewRecord bad;
  bad.angle_deg = 144;
  session.add_view(Cloud{}, bad);  // empty
  Cloud nans;
  nans.points.assign(500, Vec3f(std::nanf(""), 0, 0));
  bad.angle_deg = 168;
  session.add_view(nans, bad);
  // Random points in a 10 cm box 2 m away: no overlap with anything. (The
  // dragon's own view 7 moved 2 m away is no longer such a view: the
  // multi-start against the model finds where it fits, issue 26.)
  Cloud far;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(0.0f, 0.1f);
  for (int k = 0; k < 20000; ++k) far.points.push_back(Vec3f(2 + u(rng), u(rng), u(rng)));
  bad.angle_deg = 192;
  session.add_view(far, bad);
  const Session reopened = Session::open(session.dir());
  std::vector<RegistrationProgress> reports;
  const RegistrationResult r =
      register_session(reopened, {}, [&](const RegistrationProgress& p) { reports.push_back(p); });
  ASSERT_EQ(r.failed_views, (std::vector<int>{6, 7, 8}));
  // Progress: each stage announces itself (done 0) before its work and ends at its
  // total, so a progress bar times each stage's own work (the refinement's ICP was
  // shown as "icp done in 0.0s" and its time under the stage before).
  std::vector<std::string> stages;
  for (std::size_t k = 0; k < reports.size(); ++k) {
    const RegistrationProgress& p = reports[k];
    if (k == 0 || reports[k - 1].stage != p.stage) {
      EXPECT_EQ(p.done, 0) << p.stage;
      stages.push_back(p.stage);
    }
    if (k + 1 == reports.size() || reports[k + 1].stage != p.stage) {
      EXPECT_EQ(p.done, p.total) << p.stage;
    }
  }
  EXPECT_EQ(std::set<std::string>(stages.begin(), stages.end()).size(), stages.size())
      << "a stage came back";
  EXPECT_NE(std::find(stages.begin(), stages.end(), "refine"), stages.end());
  EXPECT_NE(r.views[6].message.find("views[6] (view_006.ply): empty view"), std::string::npos) << r.views[6].message;
  EXPECT_NE(r.views[7].message.find("views[7]"), std::string::npos) << r.views[7].message;
  // The PLY reader already refuses NaN coordinates: the view is unreadable.
  EXPECT_NE(r.views[7].message.find("non-finite"), std::string::npos) << r.views[7].message;
  EXPECT_NE(r.views[8].message.find("no overlap"), std::string::npos) << r.views[8].message;
  for (int i = 0; i < 6; ++i) {
    EXPECT_TRUE(r.views[i].registered) << i << ": " << r.views[i].message;
    ASSERT_TRUE(r.views[i].rotation_error_deg.has_value());
    EXPECT_LT(*r.views[i].rotation_error_deg, 1.0) << i;
  }
  EXPECT_GT(r.merged.size(), 20000u);
  EXPECT_FALSE(stages.empty());
  EXPECT_EQ(r.fuse_distance, 0.0);  // fusion is off by default

  // With fusion: the same poses, fewer points (the overlaps averaged), the
  // distance taken from the views' spacing.
  RegistrationParams fp;
  fp.fuse = true;
  const RegistrationResult rf = register_session(reopened, fp);
  ASSERT_EQ(rf.failed_views, r.failed_views);
  for (int i = 0; i < 6; ++i) EXPECT_TRUE(rf.poses[i].isApprox(r.poses[i], 1e-12)) << i;
  EXPECT_GT(rf.fuse_distance, 0.0002);  // every 5th point of 0.3-0.5 mm scans
  EXPECT_LT(rf.fuse_distance, 0.005);
  EXPECT_EQ(rf.fuse.input, r.merged.size());
  EXPECT_EQ(rf.fuse.output, rf.merged.size());
  EXPECT_GT(rf.fuse.fused, r.merged.size() / 5);  // neighbouring views overlap widely
  EXPECT_EQ(rf.merged.size() + rf.fuse.fused, r.merged.size());
  EXPECT_TRUE(rf.merged.has_normals());
  const auto poses = dir / "poses.yaml";
  write_poses_yaml(poses, r, reopened.manifest());
  const std::string yaml = read_file_bytes(poses);
  EXPECT_NE(yaml.find("view_008.ply"), std::string::npos);
  EXPECT_NE(yaml.find("registered: false"), std::string::npos);
  EXPECT_NE(yaml.find("matrix"), std::string::npos);

  // No usable view at all is an error, not an empty result.
  SessionManifest none;
  none.views.resize(1);
  EXPECT_THROW(register_views({Cloud{}}, none), InvalidInput);
}

}  // namespace
}  // namespace station
