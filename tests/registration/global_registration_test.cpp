// Global registration by features (capture/global_registration.h) and its use
// in register_views: the bundled dragon with nothing but the clouds, a wrong
// commanded angle, an off-turntable view.
#include "registration/global_registration.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <fstream>
#include <sstream>

#include "capture/capture.h"
#include "registration/registration.h"
#include "core/error.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "core/kdtree.h"
#include "dragon_session.h"
#include "test_util.h"

namespace station {
namespace {

SessionManifest dragon(std::vector<Cloud>& clouds) { return test::dragon_session(clouds); }

void print(const RegistrationResult& r, double secs) {
  for (std::size_t i = 0; i < r.views.size(); ++i)
    std::printf("view %2zu: %s rot %.3f deg, trans %.3f mm %s\n", i, to_string(r.views[i].initial),
                r.views[i].rotation_error_deg.value_or(-1), 1000 * r.views[i].translation_error.value_or(-1),
                r.views[i].message.c_str());
  std::printf("max %.3f deg / %.3f mm, median %.3f deg / %.3f mm, %.2f s (prep %.2f init %.2f refine %.2f)\n",
              r.max_rotation_error_deg, 1000 * r.max_translation_error, r.median_rotation_error_deg,
              1000 * r.median_translation_error, secs, r.seconds_prepare, r.seconds_initial, r.seconds_refine);
}

// Two views of the same dragon scan: view 0 and view 0 moved by a known
// large motion; the features alone find it.
TEST(GlobalRegistration, RecoversALargeKnownMotion) {
  std::vector<Cloud> clouds;
  dragon(clouds);
  const std::vector<Vec3f>& pts = clouds[0].points;
  Eigen::Matrix4d X = Eigen::Matrix4d::Identity();
  X.block<3, 3>(0, 0) = Eigen::AngleAxisd(2.0, Vec3d(0.3, 1, -0.2).normalized()).toRotationMatrix();
  X.block<3, 1>(0, 3) = Vec3d(0.1, -0.05, 0.2);
  std::vector<Vec3f> moved;
  for (const Vec3f& p : pts) moved.push_back((X.block<3, 3>(0, 0) * p.cast<double>() + X.block<3, 1>(0, 3)).cast<float>());
  GlobalRegistrationParams gp;
  gp.voxel_size = 0.004;
  const FeatureView src = make_feature_view(pts, Vec3f::Zero(), gp);
  // Normals of the moved copy, carried: the other overload.
  std::vector<Vec3f> nrm;
  {
    const PointIndex idx(pts);
    const std::vector<Vec3f> n0 = pca_normals(idx, 16, Vec3f::Zero());
    for (const Vec3f& n : n0) nrm.push_back((X.block<3, 3>(0, 0) * n.cast<double>()).cast<float>());
  }
  const FeatureView dst = make_feature_view(moved, nrm, gp);
  ASSERT_GT(src.points.size(), 200u);
  const GlobalRegistrationResult g = register_global(src, dst, gp);
  ASSERT_TRUE(g.success) << g.message;
  EXPECT_GT(g.prerejected, 0);
  const Eigen::Matrix4d E = rigid_inverse(X) * g.transform;
  EXPECT_LT(rotation_angle_deg(E), 3.0);
  EXPECT_LT((E.block<3, 1>(0, 3)).norm(), 3 * gp.voxel_size);
  // Deterministic for a seed.
  const GlobalRegistrationResult g2 = register_global(src, dst, gp);
  EXPECT_TRUE(g2.transform.isApprox(g.transform));
}

TEST(GlobalRegistration, UnrelatedCloudsFailAndBadParamsThrow) {
  // A sphere against a box: no consistent matches with enough overlap.
  const Cloud sphere = test::icosphere(3, 0.1).as_cloud();
  GlobalRegistrationParams gp;
  gp.voxel_size = 0.01;
  const FeatureView a = make_feature_view(sphere.points, Vec3f::Zero(), gp);
  const FeatureView empty = make_feature_view({}, Vec3f::Zero(), gp);
  const GlobalRegistrationResult g = register_global(empty, a, gp);
  EXPECT_FALSE(g.success);
  EXPECT_NE(g.message.find("source"), std::string::npos);
  GlobalRegistrationParams bad = gp;
  bad.voxel_size = 0;
  EXPECT_THROW(register_global(a, a, bad), InvalidInput);
  bad = gp;
  bad.edge_similarity = 1.5;
  EXPECT_THROW(make_feature_view(sphere.points, Vec3f::Zero(), bad), InvalidInput);
}

TEST(GlobalRegistration, DragonFromCloudsAlone) {
  std::vector<Cloud> clouds;
  SessionManifest m = dragon(clouds);
  ASSERT_EQ(m.views.size(), 15u);
  for (ViewRecord& v : m.views) v.angle_deg.reset();
  const auto t0 = std::chrono::steady_clock::now();
  const RegistrationResult r = register_views(clouds, m);
  print(r, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  // Issue #3: at least 13 of 15 views at the angle + no-axis accuracy (the
  // dragon test of registration_test.cpp: 0.5 deg / 2.3 mm), the rest flagged.
  // Without angles the ring is still tried as one rigid turntable, and fits.
  int good = 0;
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    const ViewDiagnostics& v = r.views[i];
    if (!v.registered) {
      EXPECT_NE(v.message.find("views[" + std::to_string(i) + "]"), std::string::npos) << v.message;
      continue;
    }
    EXPECT_EQ(v.initial, InitialPoseSource::kGlobal);
    if (v.rotation_error_deg && *v.rotation_error_deg < 0.5 && *v.translation_error < 0.0023) ++good;
  }
  EXPECT_GE(good, 13);
  EXPECT_TRUE(r.rigid_turntable);
  EXPECT_FALSE(r.axis.has_value());
}

// In one session (the dragon is slow to register, so both cases share it): a
// commanded angle 30 degrees off (view 7 says 198 instead of 168) is detected,
// recovered by global registration and warned about by name; a view without
// an angle among turntable views (taken off the table, view 10) is registered
// against the model merged from the others. The session still reaches the
// accuracy of the correct manifest.
TEST(GlobalRegistration, WrongAngleAndViewWithoutAngle) {
  std::vector<Cloud> clouds;
  SessionManifest m = dragon(clouds);
  ASSERT_EQ(m.views.size(), 15u);
  m.views[7].angle_deg = *m.views[7].angle_deg + 30;
  m.views[10].angle_deg.reset();
  const auto t0 = std::chrono::steady_clock::now();
  const RegistrationResult r = register_views(clouds, m);
  print(r, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  for (const std::string& w : r.warnings) std::printf("warning: %s\n", w.c_str());
  ASSERT_EQ(r.warnings.size(), 1u);
  EXPECT_NE(r.warnings[0].find("views[7]"), std::string::npos);
  EXPECT_TRUE(r.views[7].angle_rejected);
  EXPECT_EQ(r.views[7].initial, InitialPoseSource::kGlobal);
  EXPECT_EQ(r.views[10].initial, InitialPoseSource::kGlobal);
  EXPECT_EQ(r.views[9].initial, InitialPoseSource::kEstimatedAxis);
  EXPECT_TRUE(r.failed_views.empty());
  for (std::size_t i = 0; i < r.views.size(); ++i)
    if (i != 7) {
      EXPECT_FALSE(r.views[i].angle_rejected) << i;
    }
  ASSERT_EQ(r.views_with_reference, 15);
  // Views 7 and 10 are free in the pose graph, the 13 others on the rigid table.
  EXPECT_TRUE(r.rigid_turntable);
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_translation_error, 0.0023);
}

// The prior as a hypothesis on real scans (issue 26): the dragon session with
// its angles corrupted lands where the clean session does: every view within
// 0.5 deg and 1 mm at the object (the view's centroid) of the clean poses.
// `moves` (when given): view i's cloud was moved by moves[i] in its scanner
// frame (the object moved on the table), so its true pose is the clean one
// times moves[i]^-1; `clouds` are the moved ones.
// `max_at`: the bound at the object, metres (the 1 mm unless a case
// says why not).
void expect_as_clean(const RegistrationResult& clean, const RegistrationResult& r,
                     const std::vector<Cloud>& clouds, const char* what,
                     const std::vector<Eigen::Matrix4d>* moves = nullptr, double max_at = 0.001) {
  std::printf("%s: kept %s; %s\n", what, r.prior_kept.c_str(), r.prior_comparison.c_str());
  for (const std::string& w : r.warnings) std::printf("  warning: %s\n", w.c_str());
  EXPECT_TRUE(r.failed_views.empty()) << what;
  double worst_rot = 0, worst_at = 0;
  std::size_t worst_view = 0;
  for (std::size_t i = 0; i < r.poses.size(); ++i) {
    Vec3d c = Vec3d::Zero();
    for (const Vec3f& p : clouds[i].points) c += p.cast<double>();
    c /= double(std::max<std::size_t>(clouds[i].size(), 1));
    Eigen::Matrix4d a = rigid_inverse(clean.poses[0]) * clean.poses[i];
    if (moves) a = a * rigid_inverse((*moves)[i]);
    const Eigen::Matrix4d b = rigid_inverse(r.poses[0]) * r.poses[i];
    worst_rot = std::max(worst_rot, rotation_angle_deg(rigid_inverse(a) * b));
    const double at = ((a - b) * c.homogeneous()).norm();
    if (at > worst_at) worst_view = i;
    worst_at = std::max(worst_at, at);
  }
  std::printf("  against the clean session: %.3f deg, %.3f mm at the object (view %zu)\n", worst_rot, 1000 * worst_at,
              worst_view);
  EXPECT_LT(worst_rot, 0.5) << what;
  EXPECT_LT(worst_at, max_at) << what;
}

// The bundled dragon session and its registration with the right angles, made once
// for the tests that compare corrupted sessions with it.
struct CleanDragon {
  std::vector<Cloud> clouds;
  SessionManifest m;
  RegistrationResult clean;
};
const CleanDragon& clean_dragon() {
  static const CleanDragon d = [] {
    CleanDragon c;
    c.m = dragon(c.clouds);
    c.clean = register_views(c.clouds, c.m);
    return c;
  }();
  return d;
}

TEST(GlobalRegistration, DragonWithWrongAnglesLandsWhereTheCleanSessionDoes) {
  const auto& [clouds, m, clean] = clean_dragon();
  ASSERT_EQ(m.views.size(), 15u);
  ASSERT_TRUE(clean.failed_views.empty());
  EXPECT_TRUE(clean.prior_comparison.empty());  // nothing suspect: registered once

  SessionManifest two = m;
  *two.views[4].angle_deg += 12;
  *two.views[11].angle_deg -= 18;
  const RegistrationResult r2 = register_views(clouds, two);
  expect_as_clean(clean, r2, clouds, "two angles off by 12 and -18 deg");

  // A nominal angle list: every angle rounded to the nearest 30 degrees (the
  // true steps are 24), and three views without angle.
  SessionManifest nominal = m;
  for (ViewRecord& v : nominal.views) v.angle_deg = 30 * std::round(*v.angle_deg / 30);
  for (int i : {3, 9, 13}) nominal.views[i].angle_deg.reset();
  const RegistrationResult rn = register_views(clouds, nominal);
  expect_as_clean(clean, rn, clouds, "nominal angles, three views without angle");
  // Whichever poses are kept, the stage after knows the turntable axis (the
  // report's up, the table plane): the Cyberware's turns about y.
  ASSERT_TRUE(rn.axis.has_value());
  EXPECT_GT(std::abs(rn.axis->direction.normalized().y()), 0.99);
}


// The object moved on the table, in the dragon's frame (y up): `D` applied to
// the object for views `from`..`to` (scanner-frame clouds moved by
// X^-1 D X with X the view's reference pose). Returns each view's move.
std::vector<Eigen::Matrix4d> move_object(std::vector<Cloud>& clouds, const SessionManifest& m,
                                         const Eigen::Matrix4d& D, std::size_t from, std::size_t to) {
  std::vector<Eigen::Matrix4d> moves(clouds.size(), Eigen::Matrix4d::Identity());
  for (std::size_t i = from; i <= to; ++i) {
    const Eigen::Matrix4d& X = *m.views[i].reference_pose;
    moves[i] = rigid_inverse(X) * D * X;
    const Eigen::Matrix4f M = moves[i].cast<float>();
    for (Vec3f& p : clouds[i].points) p = M.block<3, 3>(0, 0) * p + M.block<3, 1>(0, 3);
    for (Vec3f& q : clouds[i].normals) q = M.block<3, 3>(0, 0) * q;
  }
  return moves;
}

// More of issue 26's corrupted dragon sessions: the angles of the opposite sign,
// and one view with the object shifted 3 cm. Each lands within 0.5 deg / 1 mm
// at the object of the clean session (the moved view: of the clean pose moved
// with it). And the object turned 90 degrees about its up and moved 3 cm after
// view 7 (a second pass), which misses the 1 mm (below).
TEST(GlobalRegistration, DragonWithTheSignFlippedOrTheObjectMovedLandsWhereTheCleanSessionDoes) {
  const auto& [clouds, m, clean] = clean_dragon();
  ASSERT_EQ(m.views.size(), 15u);
  ASSERT_TRUE(clean.failed_views.empty());

  SessionManifest flipped = m;
  for (ViewRecord& v : flipped.views) v.angle_deg = -*v.angle_deg;
  expect_as_clean(clean, register_views(clouds, flipped), clouds, "the angles of the opposite sign");

  Eigen::Matrix4d shift = Eigen::Matrix4d::Identity();
  shift.block<3, 1>(0, 3) = Vec3d(0.025, 0, -0.015);
  std::vector<Cloud> shifted = clouds;
  const auto shift_moves = move_object(shifted, m, shift, 6, 6);
  expect_as_clean(clean, register_views(shifted, m), shifted, "view 6's object shifted 3 cm", &shift_moves);

  Eigen::Matrix4d turn = Eigen::Matrix4d::Identity();
  turn.block<3, 3>(0, 0) = Eigen::AngleAxisd(M_PI / 2, Vec3d::UnitY()).toRotationMatrix();
  turn.block<3, 1>(0, 3) = Vec3d(0.03, 0, 0.01);
  std::vector<Cloud> turned = clouds;
  const auto turn_moves = move_object(turned, m, turn, 8, 14);
  // Against the clean session 0.46 deg / 1.13 mm at the object (view 7), over
  // the 1 mm: but the clean session's view 7 is itself 1.44 mm from
  // Stanford's pose there, and this one 0.32 mm. So the turned session is
  // asserted against Stanford's poses (the truth for the moved views: D^-1 X),
  // within the 0.5 deg / 1 mm at the object (0.37 deg / 0.58 mm
  // measured; the clean session's own worst is 0.32 deg / 1.44 mm), and
  // against the clean session within the clean session's own worst error
  // against Stanford's (2.1 mm in the scanner frame). Before 2026-12-05: a view
  // 132 deg / 107 mm off.
  // The truth of the moved views for the errors against Stanford's poses
  // (reference poses only measure): X' = D^-1 X.
  SessionManifest tm = m;
  for (std::size_t i = 8; i < 15; ++i) *tm.views[i].reference_pose = rigid_inverse(turn) * *m.views[i].reference_pose;
  const RegistrationResult rt = register_views(turned, tm);
  expect_as_clean(clean, rt, turned, "turned 90 deg and moved 3 cm after view 7", &turn_moves, 0.0021);
  for (std::size_t i = 0; i < 15; ++i)
    std::printf("  view %zu against Stanford's pose: clean %.3f deg %.3f mm, turned %.3f deg %.3f mm at the object\n", i,
                clean.views[i].rotation_error_deg.value_or(-1), 1000 * clean.views[i].object_translation_error.value_or(-1),
                rt.views[i].rotation_error_deg.value_or(-1), 1000 * rt.views[i].object_translation_error.value_or(-1));
  EXPECT_EQ(rt.views_with_reference, 15);
  EXPECT_LT(rt.max_rotation_error_deg, 0.5);
  EXPECT_LT(rt.max_object_translation_error, 0.001);
  bool regrouped = false;
  for (const std::string& w : rt.warnings)
    regrouped = regrouped || w.find("the views from views[8] (dragonStandRight_192.ply) on were registered to the "
                                    "ones before as a whole") != std::string::npos;
  EXPECT_TRUE(regrouped);
}


// Two moves on the table (issue 26, item 2, more than one): the dragon turned
// 90 deg and moved 3 cm after view 4, then turned -60 deg and moved 3 cm after
// view 9, the angles recorded as if nothing had moved. No pair across a move
// converges at the prior's poses, so the run with the angles leaves views 5-14
// held to the rest by the angles alone (before: 30-90 deg off, all counted as
// registered; only "overlap none of the other views" was said). The run
// without angles joins more views by converged pairs and agrees with the
// prior's run where that one measured, so it is kept; the two views it could
// not place (too little overlap from scratch) start from their neighbours'
// angles. Every view within the 0.5 deg / 1 mm at the object of the
// clean session (measured 0.44 deg / 0.36 mm).
TEST(GlobalRegistration, DragonMovedTwiceOnTheTableLandsRight) {
  const auto& [clouds, m, clean] = clean_dragon();
  ASSERT_EQ(m.views.size(), 15u);
  Eigen::Matrix4d first = Eigen::Matrix4d::Identity(), second = Eigen::Matrix4d::Identity();
  first.block<3, 3>(0, 0) = Eigen::AngleAxisd(M_PI / 2, Vec3d::UnitY()).toRotationMatrix();
  first.block<3, 1>(0, 3) = Vec3d(0.03, 0, 0.01);
  second.block<3, 3>(0, 0) = Eigen::AngleAxisd(-M_PI / 3, Vec3d::UnitY()).toRotationMatrix();
  second.block<3, 1>(0, 3) = Vec3d(-0.01, 0, 0.03);
  std::vector<Cloud> moved = clouds;
  const auto m1 = move_object(moved, m, first, 5, 14);
  const auto m2 = move_object(moved, m, second, 10, 14);
  std::vector<Eigen::Matrix4d> moves(15);
  SessionManifest tm = m;
  for (std::size_t i = 0; i < 15; ++i) {
    moves[i] = m2[i] * m1[i];
    const Eigen::Matrix4d D = i >= 10 ? Eigen::Matrix4d(second * first) : i >= 5 ? first : Eigen::Matrix4d::Identity();
    *tm.views[i].reference_pose = rigid_inverse(D) * *m.views[i].reference_pose;
  }
  const RegistrationResult r = register_views(moved, tm);
  expect_as_clean(clean, r, moved, "moved twice (after views 4 and 9)", &moves);
  EXPECT_EQ(r.prior_kept, "no prior");
  for (std::size_t i = 0; i < 15; ++i)
    std::printf("  view %zu against Stanford's pose: %.3f deg %.3f mm at the object\n", i,
                r.views[i].rotation_error_deg.value_or(-1), 1000 * r.views[i].object_translation_error.value_or(-1));
  // Views 11 and 12 were placed from their neighbours' angles.
  EXPECT_EQ(r.views[11].prior, PriorUse::kUsed);
  EXPECT_EQ(r.views[12].prior, PriorUse::kUsed);
  EXPECT_EQ(r.views[13].prior, PriorUse::kIgnored);
  bool said = false, between = false, nowhere = false;
  for (const std::string& w : r.warnings) {
    said = said || w.find("started from the angles of neighbours") != std::string::npos;
    // Said as a move between passes, not as a turntable that did not turn.
    between = between || w.find("fit 3 runs of views apart (views[0]-views[4], views[5]-views[9], "
                                "views[10]-views[14]), each turning as its angles say") != std::string::npos;
    nowhere = nowhere || w.find("fit the registered poses nowhere") != std::string::npos;
  }
  EXPECT_TRUE(said);
  EXPECT_TRUE(between);
  EXPECT_FALSE(nowhere);
}

// Issue 26's headline session, on the dragon: six turntable views with nominal
// angles (0, 45, 90, 180, 270, 315 for the scans at 0, 48, 96, 168, 264, 312: one
// 12 deg off), four views without angle (24, 120, 216, 336) after them, and the
// object moved 5 cm and turned 10 deg on the table after the fourth view, the
// angles recorded as if it had not. Before: the pairs across the move failed and
// the angles alone held the moved views where the object no longer was (4.3 deg /
// 50 mm off, said only as "overlap none of the other views"). Now that group,
// unjoined by any pair, is registered to the others as a whole
// (RegistrationParams::place_unlinked) and every view lands within the issue's
// 0.5 deg / 1 mm at the object of the clean 15-view session.
TEST(GlobalRegistration, DragonWithNominalAnglesMovedOnTheTableLandsWhereTheCleanSessionDoes) {
  const auto& [clouds, m, clean] = clean_dragon();
  ASSERT_EQ(m.views.size(), 15u);
  // (index in the clean session, nominal angle or none, moved)
  struct Pick {
    int view;
    double angle;  // < 0: none
    bool moved;
  };
  const Pick picks[] = {{0, 0, false},  {2, 45, false},  {4, 90, false},  {7, 180, false}, {11, 270, true},
                        {13, 315, true}, {1, -1, false},  {5, -1, false},  {9, -1, true},   {14, -1, true}};
  Eigen::Matrix4d D = Eigen::Matrix4d::Identity();
  D.block<3, 3>(0, 0) = Eigen::AngleAxisd(10 * M_PI / 180, Vec3d::UnitY()).toRotationMatrix();
  D.block<3, 1>(0, 3) = Vec3d(0.03, 0, 0.04);
  std::vector<Cloud> sub;
  SessionManifest sm;
  sm.scanner = m.scanner;
  RegistrationResult sub_clean;  // the clean session's poses of the picked views
  std::vector<Eigen::Matrix4d> moves;
  for (const Pick& k : picks) {
    sub.push_back(clouds[std::size_t(k.view)]);
    ViewRecord v = m.views[std::size_t(k.view)];
    if (k.angle >= 0) v.angle_deg = k.angle;
    else v.angle_deg.reset();
    SessionManifest one;
    one.views = {m.views[std::size_t(k.view)]};
    std::vector<Cloud> c1 = {sub.back()};
    moves.push_back(k.moved ? move_object(c1, one, D, 0, 0)[0] : Eigen::Matrix4d::Identity());
    sub.back() = c1[0];
    if (k.moved) *v.reference_pose = rigid_inverse(D) * *v.reference_pose;
    sm.views.push_back(v);
    sub_clean.poses.push_back(clean.poses[std::size_t(k.view)]);
  }
  const RegistrationResult r = register_views(sub, sm);
  expect_as_clean(sub_clean, r, sub, "nominal angles, four views without, moved 5 cm after the fourth", &moves);
  bool said = false;
  for (const std::string& w : r.warnings)
    said = said || w.find("were registered to the others as a whole: the object moved on the table") != std::string::npos;
  EXPECT_TRUE(said);
  // The moved views' angles are off by the move: not named one by one as wrong.
  for (const std::string& w : r.warnings)
    EXPECT_EQ(w.find("(dragonStandRight_264.ply): commanded angle"), std::string::npos) << w;
  // The angle error column is the kept poses' (registered minus commanded: the
  // nominal angles are 3-12 deg off, the moved views turned 10 deg more), not the
  // run without angles', which placed the moved views about 100 deg off.
  for (std::size_t i = 0; i < sm.views.size(); ++i) {
    if (!sm.views[i].angle_deg) continue;
    ASSERT_TRUE(r.views[i].angle_error_deg.has_value()) << i;
    EXPECT_LT(std::abs(*r.views[i].angle_error_deg), 25.0) << "view " << i;
  }
  // The scan at 168 deg recorded as 180 is named, by how much the kept poses say.
  double named_off = -1;
  for (const std::string& w : r.warnings) {
    const std::string say = "(dragonStandRight_168.ply): commanded angle 180 deg is ";
    const std::size_t at = w.find(say);
    if (at != std::string::npos) named_off = std::stod(w.substr(at + say.size()));
  }
  EXPECT_GT(named_off, 8.0);   // 12 deg off, as the nominal angles' consensus puts it
  EXPECT_LT(named_off, 20.0);
  // Without the placement, the session as before: the moved views far off.
  RegistrationParams off;
  off.place_unlinked = false;
  const RegistrationResult before = register_views(sub, sm, off);
  EXPECT_GT(before.max_object_translation_error, 0.01);
}

// The dragon's files in a shell glob's order (dragonStandRight_0, _120, _144,
// ..., _24, _240, ...: lexical, not the turntable's) and without angles, as
// `station import dragonStandRight_*.ply` makes it without --step. With the
// chain's unplaced views retried against the chained model alone, 9 of 15
// registered (the refinement paired views by their neighbours in the list,
// which do not overlap); without angles every view is now paired by overlap:
// 11 of 15, the four from 144 to 216 degrees failed by name. No
// view may come out wrong (a second pass against the widened model placed
// three of the back views 168 deg off; it is not done).
TEST(GlobalRegistration, DragonInAShellGlobsOrderWithoutAngles) {
  std::vector<Cloud> clouds;
  const SessionManifest m = dragon(clouds);
  ASSERT_EQ(m.views.size(), 15u);
  std::vector<std::size_t> order(m.views.size());
  for (std::size_t k = 0; k < order.size(); ++k) order[k] = k;
  std::sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return m.views[a].file < m.views[b].file; });
  ASSERT_EQ(m.views[order[1]].file, "dragonStandRight_120.ply");
  SessionManifest g = m;
  g.views.clear();
  std::vector<Cloud> gc;
  for (std::size_t k : order) {
    ViewRecord v = m.views[k];
    v.angle_deg.reset();
    g.views.push_back(v);
    gc.push_back(clouds[k]);
  }
  const RegistrationResult r = register_views(gc, g);
  int registered = 0;
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    std::printf("%s: %s, %.3f deg, %.3f mm at the object\n", g.views[i].file.c_str(),
                r.views[i].registered ? "registered" : "failed", r.views[i].rotation_error_deg.value_or(-1),
                1000 * r.views[i].object_translation_error.value_or(-1));
    if (!r.views[i].registered) continue;
    ++registered;
    ASSERT_TRUE(r.views[i].rotation_error_deg.has_value()) << i;
    // Against Stanford's poses: within the clean session's own worst (0.33 deg, 2.1 mm).
    EXPECT_LT(*r.views[i].rotation_error_deg, 0.5) << g.views[i].file;
    EXPECT_LT(*r.views[i].object_translation_error, 0.0021) << g.views[i].file;
  }
  // Every view since the chain waits for a confident fit (two failed by name before).
  EXPECT_EQ(registered, 15);
}

// The scans given in a shuffled order with --step 24 (angles 0, 24, ... in the order
// given, so all but a few wrong): found by a campaign on the full scans, where seven
// views came out 167-171 deg off with exit 0 (two dragons merged), and here four views
// 103 deg off and one failed. The chain took weak fits to views far round the object
// (0.175 for two scans 120 deg apart); now those wait for a confident one.
TEST(GlobalRegistration, DragonScansInAShuffledOrderLandRight) {
  std::vector<Cloud> clouds;
  const SessionManifest m = dragon(clouds);
  ASSERT_EQ(m.views.size(), 15u);
  // The campaign's order, by angle: 168, 24, 312, 96, 0, 240, 144, 48, 288, 192, 72, 336, 216, 120, 264.
  const std::vector<std::size_t> order = {7, 1, 13, 4, 0, 10, 6, 2, 12, 8, 3, 14, 9, 5, 11};
  SessionManifest s = m;
  s.views.clear();
  std::vector<Cloud> sc;
  for (std::size_t k = 0; k < order.size(); ++k) {
    ViewRecord v = m.views[order[k]];
    v.angle_deg = 24.0 * double(k);
    s.views.push_back(v);
    sc.push_back(clouds[order[k]]);
  }
  const RegistrationResult r = register_views(sc, s);
  std::printf("kept %s; %s\n", r.prior_kept.c_str(), r.prior_comparison.c_str());
  for (const std::string& w : r.warnings) std::printf("  warning: %s\n", w.c_str());
  EXPECT_TRUE(r.failed_views.empty());
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    ASSERT_TRUE(r.views[i].registered) << s.views[i].file;
    ASSERT_TRUE(r.views[i].rotation_error_deg.has_value()) << i;
    EXPECT_LT(*r.views[i].rotation_error_deg, 0.5) << s.views[i].file;
    EXPECT_LT(*r.views[i].object_translation_error, 0.0021) << s.views[i].file;
  }
}

}  // namespace
}  // namespace station
