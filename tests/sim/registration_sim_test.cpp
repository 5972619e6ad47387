// Registration (capture/registration.h) of a simulated session with known
// truth: noisy depth, turntable angles off by up to 3 degrees.
#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <random>
#include <set>
#include <tuple>

#include "capture/capture.h"
#include "registration/registration.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "sim/sim.h"
#include "sim_test_util.h"
#include "test_util.h"

namespace station {
namespace {

// An asymmetric object: three boxes of different sizes (the planes face every
// direction, so no motion is left free), standing on the table (z up).
Mesh blocks() {
  Mesh m;
  const auto add = [&](const Vec3f& lo, const Vec3f& hi) {
    const Mesh b = test::box(lo, hi);
    const int base = int(m.vertices.size());
    m.vertices.insert(m.vertices.end(), b.vertices.begin(), b.vertices.end());
    for (const Face& f : b.faces) m.faces.push_back(f + Face::Constant(base));
  };
  add(Vec3f(-0.05f, -0.03f, 0.0f), Vec3f(0.04f, 0.03f, 0.05f));
  add(Vec3f(-0.02f, -0.05f, 0.05f), Vec3f(0.03f, 0.01f, 0.11f));
  add(Vec3f(0.01f, 0.0f, 0.11f), Vec3f(0.035f, 0.04f, 0.14f));
  return m;
}

// A session of `views` views taken by the simulated scanner `uri` on the simulated
// turntable into `folder`, the first at `start_deg`; crop: to the working volume.
Session capture_sim(const std::filesystem::path& folder, const std::string& uri, int views,
                    double start_deg = 0, bool crop = true) {
  DeviceRegistry reg = test::sim_registry();
  auto scanner = reg.make_scanner(uri);
  auto table = reg.make_turntable("sim:turntable");
  scanner->open();
  table->open();
  Session session = Session::create(folder, SessionManifest{});
  CaptureParams cp;
  cp.views = views;
  cp.start_deg = start_deg;
  cp.crop = crop;
  run_capture(*scanner, *table, session, cp);
  return session;
}

// 12 simulated views of `mesh` with depth noise 0.2 mm (0.1 % of the objects'
// diagonal, about 0.2 m), and the prior as the issue describes it: every
// angle but the first off by up to 3 degrees, the axis 2 % of the diagonal
// off sideways. Returns the clouds; `prior` gets the perturbed manifest.
std::vector<Cloud> scan_with_prior_off(const test::TempDir& dir, const Mesh& mesh, int noise_seed,
                                       unsigned angle_seed, double diagonal, SessionManifest& prior) {
  write_ply(dir / "object.ply", mesh);
  Session session = capture_sim(dir / "scan",
                                "sim:synthetic?mesh=" + (dir / "object.ply").string() +
                                    "&noise=0.0002&width=320&height=240&color=0&seed=" + std::to_string(noise_seed),
                                12);
  EXPECT_EQ(session.manifest().views.size(), 12u);
  prior = session.manifest();
  EXPECT_TRUE(prior.axis.has_value());
  std::mt19937 rng(angle_seed);
  std::uniform_real_distribution<double> off(-3, 3);
  for (std::size_t i = 1; i < prior.views.size(); ++i) *prior.views[i].angle_deg += off(rng);
  if (prior.axis) prior.axis->point += 0.02 * diagonal * prior.axis->direction.normalized().unitOrthogonal();
  std::vector<Cloud> clouds;
  for (std::size_t i = 0; i < prior.views.size(); ++i) clouds.push_back(session.load_view(i));
  return clouds;
}

TEST(SimRegistration, NoisyScanWithAnglesOffByThreeDegrees) {
  test::TempDir dir;
  SessionManifest noisy;
  const std::vector<Cloud> clouds = scan_with_prior_off(dir, blocks(), 3, 11, 0.19, noisy);
  ASSERT_EQ(clouds.size(), 12u);
  // The blocks' faces are all axis-aligned and views 0 and 6 look straight at
  // them, so sliding along a face is barely held between neighbouring views:
  // with free poses views 1-5 slide by about 0.9 mm (the truth fits the data no
  // better: same pair residual). The rigid turntable (default) holds them.
  RegistrationParams free_params;
  free_params.rigid_turntable = RigidTurntable::kOff;
  const RegistrationResult f = register_views(clouds, noisy, free_params);
  const RegistrationResult r = register_views(clouds, noisy);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.views_with_reference, 12);
  for (const RegistrationResult* x : {&f, &r})
    std::printf("sim, %s: max %.4f deg / %.4f mm (at the object %.4f mm), median %.4f deg; %.2f s\n",
                x->rigid_turntable ? "rigid turntable" : "free poses", x->max_rotation_error_deg,
                1000 * x->max_translation_error, 1000 * x->max_object_translation_error,
                x->median_rotation_error_deg, x->seconds_total);
  std::printf("pair residual %.4f mm, under the truth %.4f mm\n", 1000 * r.mean_pair_rmse,
              1000 * r.mean_reference_pair_rmse.value_or(-1));
  for (std::size_t i = 0; i < r.views.size(); ++i)
    std::printf("  view %2zu: %.4f deg, %.4f mm, at the object %.4f mm\n", i, *r.views[i].rotation_error_deg,
                1000 * *r.views[i].translation_error, 1000 * *r.views[i].object_translation_error);
  RecordProperty("max_rotation_error_deg", std::to_string(r.max_rotation_error_deg));
  EXPECT_FALSE(f.rigid_turntable);
  EXPECT_GT(f.max_object_translation_error, 5e-4);
  // The issue: under 0.1 degree and 0.05 % of the diagonal (0.095 mm) for
  // every view. Reached at the object: 0.025 deg, 0.024 mm. In the scanner
  // frame (0.45 m from the object) the translation also carries the rotation
  // error times that lever arm: 0.2 mm.
  EXPECT_TRUE(r.rigid_turntable);
  EXPECT_LT(r.max_rotation_error_deg, 0.1);
  EXPECT_LT(r.max_object_translation_error, 0.0005 * 0.19);
  EXPECT_LT(r.max_translation_error, 0.0004);
  for (const ViewDiagnostics& v : r.views) EXPECT_EQ(v.initial, InitialPoseSource::kTurntableAxis);
}

// The same on a generic shape, with the prior as far off as the issue allows:
// the fandisk CAD part (tests/data/consolidation, curved and flat faces, no
// symmetry), scaled to 15 cm and stood on the table.
// The blocks above are a hard case for point-to-plane ICP: their faces are all
// axis-aligned and views 0 and 6 look straight at them, so sliding along a
// face is barely constrained between neighbouring views there.
// The fandisk CAD part scaled to 15 cm and stood on the table; its diagonal.
Mesh fandisk_part(double& diag) {
  Mesh part = read_mesh(test::source_dir() / "tests/data/consolidation/fandisk.off");
  for (Vec3f& v : part.vertices) v = 0.15f * (v + Vec3f(0, 0, 0.5f));
  diag = 0.15 * std::sqrt(0.9206 * 0.9206 + 0.5111 * 0.5111 + 1.0);
  return part;
}

TEST(SimRegistration, NoisyFandiskWithPriorOff) {
  test::TempDir dir;
  double diag = 0;
  const Mesh part = fandisk_part(diag);
  SessionManifest noisy;
  const std::vector<Cloud> clouds = scan_with_prior_off(dir, part, 5, 13, diag, noisy);
  ASSERT_EQ(clouds.size(), 12u);
  const RegistrationResult r = register_views(clouds, noisy);
  EXPECT_TRUE(r.failed_views.empty());
  ASSERT_EQ(r.views_with_reference, 12);
  std::printf("fandisk (diagonal %.1f mm): max %.4f deg / %.4f mm (at the object %.4f mm), median %.4f deg; %.2f s\n",
              1000 * diag, r.max_rotation_error_deg, 1000 * r.max_translation_error,
              1000 * r.max_object_translation_error, r.median_rotation_error_deg, r.seconds_total);
  for (std::size_t i = 0; i < r.views.size(); ++i)
    std::printf("  view %2zu: %.4f deg, %.4f mm, at the object %.4f mm\n", i, *r.views[i].rotation_error_deg,
                1000 * *r.views[i].translation_error, 1000 * *r.views[i].object_translation_error);
  // Every pair of the last round converged (two of them used to cycle at the
  // final distance and were dropped; icp.cpp now damps such cycles).
  for (const PairDiagnostics& p : r.pairs) {
    if (p.round == 2) {
      EXPECT_TRUE(p.converged) << p.from << "-" << p.to << ": " << p.message;
    }
  }
  // The issue: every view under 0.1 degree and 0.05 % of the diagonal
  // (0.11 mm). With these seeds: 0.033 degree and 0.017 mm at the object
  // (0.22 mm in the scanner frame 0.45 m away, the rotation error times that
  // lever arm). Over other noise and angle seeds (6/14, 7/21, 9/3): 0.021-0.027
  // degree, 0.016-0.028 mm at the object. With free poses (before the rigid
  // turntable): 0.052-0.090 degree and 0.07-0.33 mm at the object.
  EXPECT_TRUE(r.rigid_turntable);
  EXPECT_LT(r.max_rotation_error_deg, 0.1);
  EXPECT_LT(r.max_object_translation_error, 0.0005 * diag);
}

// A session that is not one rigid turntable: the object was nudged 6 mm
// across the table before the second half of the views (simulated by moving
// those views' clouds). The rigid solution cannot explain that, so it is
// refused with a warning, and the free poses register every view.
TEST(SimRegistration, ObjectMovedOnTheTableKeepsTheFreePoses) {
  test::TempDir dir;
  double diag = 0;
  const Mesh part = fandisk_part(diag);
  SessionManifest noisy;
  std::vector<Cloud> clouds = scan_with_prior_off(dir, part, 5, 13, diag, noisy);
  ASSERT_EQ(clouds.size(), 12u);
  // The object moves 6 mm along the scanner's x: views 6-11 see it there.
  const Vec3f shift(0.006f, 0, 0);
  for (std::size_t i = 6; i < clouds.size(); ++i) {
    for (Vec3f& p : clouds[i].points) p += shift;
    Eigen::Matrix4d& ref = *noisy.views[i].reference_pose;
    ref = ref * (Eigen::Matrix4d() << 1, 0, 0, -shift.x(), 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1).finished();
  }
  const RegistrationResult r = register_views(clouds, noisy);
  for (const std::string& w : r.warnings) std::printf("warning: %s\n", w.c_str());
  std::printf("moved object: max %.4f deg, %.4f mm at the object; rigid deviation %.3f deg / %.3f mm\n",
              r.max_rotation_error_deg, 1000 * r.max_object_translation_error, r.rigid_deviation_deg,
              1000 * r.rigid_deviation);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_FALSE(r.rigid_turntable);
  EXPECT_GT(r.rigid_deviation, 0.01 * diag);
  ASSERT_FALSE(r.warnings.empty());
  EXPECT_NE(r.warnings.back().find("rigid turntable"), std::string::npos) << r.warnings.back();
  EXPECT_LT(r.max_rotation_error_deg, 0.2);
  EXPECT_LT(r.max_object_translation_error, 0.001);
}

// The prior as a hypothesis (issue 26): corrupted copies of the simulated
// fandisk session, each registered and compared with the truth.
void print_prior(const char* what, const RegistrationResult& r) {
  std::printf("%s: kept %s; %s\n  max %.4f deg, %.4f mm at the object; %d failed; %.1f s\n", what,
              r.prior_kept.c_str(), r.prior_comparison.c_str(), r.max_rotation_error_deg,
              1000 * r.max_object_translation_error, int(r.failed_views.size()), r.seconds_total);
  for (const std::string& w : r.warnings) std::printf("  warning: %s\n", w.c_str());
  for (std::size_t i = 0; i < r.views.size(); ++i)
    std::printf("  view %2zu: prior %-9s angle error %7.2f deg, %.4f deg, %.4f mm at the object\n", i,
                to_string(r.views[i].prior), r.views[i].angle_error_deg.value_or(0.0),
                r.views[i].rotation_error_deg.value_or(-1), 1000 * r.views[i].object_translation_error.value_or(-1));
}

// The object moved on the table (object frame: z up): turned by `deg` about its up,
// then shifted by `shift`.
Eigen::Matrix4d table_move(double deg, const Vec3d& shift) {
  Eigen::Matrix4d D = Eigen::Matrix4d::Identity();
  D.block<3, 3>(0, 0) = Eigen::AngleAxisd(deg * M_PI / 180, Vec3d::UnitZ()).toRotationMatrix();
  D.block<3, 1>(0, 3) = shift;
  return D;
}

// Every view's angle error within `limit` degrees (the prior's own 3 degrees, plus
// the registration's) and no view named as a wrong angle: where the object moved, its
// runs' angles are off together by the move, which the warnings about it explain.
void expect_no_angle_named_wrong(const RegistrationResult& r, double limit = 4.0) {
  for (const std::string& w : r.warnings) EXPECT_EQ(w.find("deg off what the other views"), std::string::npos) << w;
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    ASSERT_TRUE(r.views[i].angle_error_deg.has_value()) << i;
    EXPECT_LT(std::abs(*r.views[i].angle_error_deg), limit) << i;
  }
}

struct PriorCase {
  test::TempDir dir;
  double diag = 0;
  SessionManifest m;
  std::vector<Cloud> clouds;
  PriorCase() {
    const Mesh part = fandisk_part(diag);
    clouds = scan_with_prior_off(dir, part, 5, 13, diag, m);
  }
  // The object moved on the table by D (object frame: z up) before views
  // from..to, which are scanned again with it there (the scanner sees the sides
  // the move turned towards it, unlike move_object's rigidly moved clouds); their
  // truth is D^-1 X.
  void rescan_moved(const Eigen::Matrix4d& D, std::size_t from, std::size_t to) {
    Mesh moved = fandisk_part(diag);
    const Eigen::Matrix4f Df = D.cast<float>();
    for (Vec3f& v : moved.vertices) v = Df.block<3, 3>(0, 0) * v + Df.block<3, 1>(0, 3);
    const std::string name = "moved_" + std::to_string(from);
    write_ply(dir / (name + ".ply"), moved);
    Session again = capture_sim(dir / name,
                                "sim:synthetic?mesh=" + (dir / (name + ".ply")).string() +
                                    "&noise=0.0002&width=320&height=240&color=0&seed=5",
                                int(m.views.size()));
    for (std::size_t i = from; i <= to; ++i) {
      clouds[i] = again.load_view(i);
      m.views[i].reference_pose = rigid_inverse(D) * *again.manifest().views[i].reference_pose;
    }
  }
  // The object moved on the table by D (object frame: z up) for views
  // from..to: their clouds moved by X^-1 D X, their truth by D^-1 X.
  void move_object(const Eigen::Matrix4d& D, std::size_t from, std::size_t to) {
    for (std::size_t i = from; i <= to; ++i) {
      Eigen::Matrix4d& X = *m.views[i].reference_pose;
      const Eigen::Matrix4f M = (rigid_inverse(X) * D * X).cast<float>();
      for (Vec3f& p : clouds[i].points) p = M.block<3, 3>(0, 0) * p + M.block<3, 1>(0, 3);
      for (Vec3f& q : clouds[i].normals) q = M.block<3, 3>(0, 0) * q;
      X = rigid_inverse(D) * X;
    }
  }
};

TEST(SimRegistration, ViewsWithWrongAnglesAreRegisteredWithoutThem) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  *c.m.views[3].angle_deg += 15;
  *c.m.views[8].angle_deg -= 20;
  std::vector<std::string> stages;
  const RegistrationResult r = register_views(c.clouds, c.m, {}, [&](const RegistrationProgress& p) {
    if (stages.empty() || stages.back() != p.stage) stages.push_back(p.stage);
  });
  // The extra runs' stages come under their own names: each stage once.
  EXPECT_EQ(std::set<std::string>(stages.begin(), stages.end()).size(), stages.size());
  EXPECT_NE(std::find(stages.begin(), stages.end(), "without angles: refine"), stages.end());
  print_prior("two angles off by 15 and -20 deg", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.views_with_reference, 12);
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  // Both wrong angles are found and measured (the others are off by the
  // prior's 3 degrees at most, plus the registration's error).
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    ASSERT_TRUE(r.views[i].angle_error_deg.has_value()) << i;
    const double e = std::abs(*r.views[i].angle_error_deg);
    if (i == 3 || i == 8) EXPECT_GT(e, 12.0) << i;
    else EXPECT_LT(e, 4.0) << i;
  }
}

TEST(SimRegistration, AnglesOfTheOppositeSignAreFoundAndCorrected) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  for (ViewRecord& v : c.m.views) *v.angle_deg = -*v.angle_deg;
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("angles of the opposite sign", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  EXPECT_NE(r.prior_kept, "prior");
}

TEST(SimRegistration, StepIndicesForDegreesAreFoundAndCorrected) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  for (std::size_t i = 0; i < c.m.views.size(); ++i) c.m.views[i].angle_deg = double(i);  // 0, 1, 2, ... (30 deg steps)
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("step indices for degrees", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
}

TEST(SimRegistration, ExtraViewsWithoutAngleJoinTheModel) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  for (int i : {2, 7, 10}) c.m.views[i].angle_deg.reset();
  // With the two best RANSAC hypotheses refined (the old default), view 2 came
  // out 33 degrees off (a near-symmetric fit of the fandisk); six find it.
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("three views without angle", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_TRUE(r.axis.has_value());  // the session's, also for prior-free poses
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
}

// Bad input for the prior check: every view the same cloud (the table never
// turned) and one view of 10 points. A clear word on the angles, the tiny view
// failed by name, no crash.
TEST(SimRegistration, IdenticalViewsAndATinyViewAreToldApart) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  for (std::size_t i = 1; i < c.clouds.size(); ++i) c.clouds[i] = c.clouds[0];
  c.clouds[5].points.resize(10);
  c.clouds[5].normals.clear();
  c.clouds[5].colours.clear();
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("identical views, one of 10 points", r);
  ASSERT_FALSE(r.views[5].registered);
  EXPECT_NE(r.views[5].message.find("views[5]"), std::string::npos) << r.views[5].message;
  bool told = false;
  for (const std::string& w : r.warnings) told = told || w.find("did the turntable turn") != std::string::npos;
  EXPECT_TRUE(told);
  // The copies are named, once (import warned of them; register did not).
  ASSERT_FALSE(r.warnings.empty());
  EXPECT_EQ(r.warnings.front().rfind("views[1] (view_001.ply), views[2] (view_002.ply), ", 0), 0u) << r.warnings.front();
  EXPECT_NE(r.warnings.front().find(" and views[11] (view_011.ply) have the same points as views[0] (view_000.ply): "
                                    "the same scan recorded twice?"),
            std::string::npos)
      << r.warnings.front();
  EXPECT_EQ(r.warnings.front().find("views[5]"), std::string::npos) << r.warnings.front();
}

// The object moved on the table (issue 26): 2 cm across the table before the
// second half of the views. Found and placed between views 5 and 6; every view
// still registered within 0.5 deg / 1 mm at the object of the truth.
TEST(SimRegistration, AnObjectThatMovedOnTheTableIsFoundBetweenTheRightViews) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  const Vec3f shift(0.02f, 0, 0);
  for (std::size_t i = 6; i < c.clouds.size(); ++i) {
    for (Vec3f& p : c.clouds[i].points) p += shift;
    Eigen::Matrix4d& ref = *c.m.views[i].reference_pose;
    ref = ref * (Eigen::Matrix4d() << 1, 0, 0, -shift.x(), 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1).finished();
  }
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("object moved 2 cm after view 5", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  bool found = false;
  for (const std::string& w : r.warnings)
    found = found || w.find("moved on the table between views[5] (view_005.ply) and views[6]") != std::string::npos;
  EXPECT_TRUE(found);
}

// The object knocked on the table after view 5 (20 degrees about the table's up
// and 2 cm across, in the object frame): each run of views turns about the one
// axis, and the two runs are held so (issue 26, item 2), every view within
// 0.5 deg / 1 mm of the truth at the object, the move named.
TEST(SimRegistration, AKnockedObjectIsRegisteredAsTwoTurntableRuns) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  ASSERT_TRUE(c.m.axis.has_value());
  const Eigen::Matrix4d D = table_move(20, Vec3d(0.02, 0.01, 0));
  c.move_object(D, 6, 11);
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("object knocked after view 5", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.turntable_groups, 2);
  // The prior check's corrected run turns views 6-11 together by their shared
  // 20-degree error (a move, not six wrong angles) and registers every view;
  // dropping their angles instead registered 7 of 12.
  EXPECT_NE(r.prior_comparison.find("corrected angles: 12 of 12 views"), std::string::npos) << r.prior_comparison;
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  bool named = false;
  for (const std::string& w : r.warnings)
    named = named || w.find("moved between views[5] (view_005.ply) and views[6]") != std::string::npos;
  EXPECT_TRUE(named);
}

// The object knocked hard after view 5: a quarter turn about the table's up
// and 3 cm across (object frame), the later views scanned with it there. The
// second run is registered to the first as a whole and the two runs are held on
// the one axis; its angles, all a quarter turn off together, are explained by the
// move. Before, the report fitted one offset to every angle: the first six views
// were named as 90 degrees off (either half is as large), and the refinement's
// turntable prior between views 5 and 6 still said the unturned angles.
TEST(SimRegistration, AnObjectTurnedAQuarterOnTheTableIsRegisteredAsTwoRuns) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  const Eigen::Matrix4d D = table_move(90, Vec3d(0.03, 0.01, 0));
  c.rescan_moved(D, 6, 11);
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("object turned 90 deg after view 5", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.turntable_groups, 2);
  EXPECT_EQ(r.moved_after_view, 6);
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  expect_no_angle_named_wrong(r);  // within its run, each is off by the prior's 3 degrees at most
}

// The object knocked twice: 20 degrees and 2 cm after view 3, then -30 degrees and
// 2 cm more after view 7, each run scanned with it where it then stood. No two runs
// explain the motions, three do: held so (three bases on the one axis), both moves
// named, and no angle named wrong (each run's angles are off by its moves together).
// Before, the free poses were kept (as accurate here) and views 4-7 were each named
// as 22-26 deg off.
TEST(SimRegistration, AnObjectKnockedTwiceIsRegisteredAsThreeTurntableRuns) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  const Eigen::Matrix4d D = table_move(20, Vec3d(0.02, 0.01, 0));
  const Eigen::Matrix4d E = table_move(-30, Vec3d(-0.01, 0.02, 0));
  c.rescan_moved(D, 4, 7);
  c.rescan_moved(E * D, 8, 11);
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("knocked twice", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  EXPECT_EQ(r.turntable_groups, 3);
  EXPECT_EQ(r.run_starts, (std::vector<int>{4, 8}));
  bool named = false;
  for (const std::string& w : r.warnings) {
    named = named || w.find("moved between views[3] (view_003.ply) and views[4] (view_004.ply), and between "
                            "views[7] (view_007.ply) and views[8] (view_008.ply)") != std::string::npos;
    EXPECT_EQ(w.find("deg off what the other views"), std::string::npos) << w;
  }
  EXPECT_TRUE(named);
}

// Every one of `views` views registered, each within the issue's 0.5 deg / 1 mm
// (at the object) of the truth.
void expect_all_within_targets(const RegistrationResult& r, int views, const std::string& what = "") {
  EXPECT_TRUE(r.failed_views.empty()) << what;
  EXPECT_EQ(r.views_with_reference, views) << what;
  EXPECT_LT(r.max_rotation_error_deg, 0.5) << what;
  EXPECT_LT(r.max_object_translation_error, 0.001) << what;
}

// The views of `session` as recorded.
std::vector<Cloud> views_of(const Session& session) {
  std::vector<Cloud> clouds;
  for (std::size_t i = 0; i < session.manifest().views.size(); ++i) clouds.push_back(session.load_view(i));
  return clouds;
}

// A sparse session: four views 90 degrees apart of the bottle at 200x150 (as `station scan --views 4 --set width=200 --set height=150` makes):
// neighbouring views overlap too little for ICP, so no pair converges. Each view
// is held where the calibrated turntable puts it (said), not failed. Before, every
// view but the first failed, and the run without angles was kept, whose one pair
// had converged half a turn off: two views 179 deg off, exit 0.
TEST(SimRegistration, ASparseSessionIsHeldByTheTurntable) {
  test::TempDir dir;
  Session session = capture_sim(dir / "scan",
                                "sim:synthetic?mesh=" + (test::source_dir() / "data/mustard_bottle/textured.obj").string() +
                                    "&noise=0.0005&width=200&height=150&seed=1",
                                4);
  const std::vector<Cloud> clouds = views_of(session);
  ASSERT_EQ(clouds.size(), 4u);
  const RegistrationResult r = register_views(clouds, session.manifest());
  print_prior("four views 90 degrees apart", r);
  expect_all_within_targets(r, 4);
  int held = 0;
  for (const std::string& w : r.warnings) held += w.find("held to them by the turntable angles alone") != std::string::npos;
  EXPECT_GE(held, 1);
}

// The first four of twelve table views recorded without an angle, the others with
// the right ones (a campaign's case, issue 26's "views without angle"): each is
// registered against the model of the angled views, which saw the other side of the
// bottle; there its half-turned twin overlaps better (0.95 against 0.64-0.76) than
// its right pose, which sees a side no angled view saw. All four came out 178-180
// deg off, exit 0, without a warning. Now the turn their neighbours' angles put them
// at (capture order) decides between the twin and a pose near it.
TEST(SimRegistration, TableViewsWithoutAngleBetweenAngledOnesLandNotHalfTurned) {
  test::TempDir dir;
  Session session = capture_sim(dir / "scan",
                                "sim:synthetic?mesh=" + (test::source_dir() / "data/mustard_bottle/textured.obj").string() +
                                    "&noise=0.0005&dropout=0.01&color_noise=2&width=320&height=240&seed=1",
                                12);
  const std::vector<Cloud> clouds = views_of(session);
  ASSERT_EQ(clouds.size(), 12u);
  SessionManifest m = session.manifest();
  for (int i : {0, 1, 2, 3}) m.views[std::size_t(i)].angle_deg.reset();
  const RegistrationResult r = register_views(clouds, m);
  print_prior("views 0-3 without angle", r);
  expect_all_within_targets(r, 12);
}

// `views` views at 320x240 from 0.45 m of the bundled textured object `object`
// (a folder of data/; or a mesh file of the source tree, with `extra` options),
// the session's manifest in `m`.
std::vector<Cloud> sparse_scan(const test::TempDir& dir, const std::string& object, int views, SessionManifest& m,
                               const std::string& extra = "") {
  const std::filesystem::path mesh = object.find('.') == std::string::npos
                                         ? test::source_dir() / "data" / object / "textured.obj"
                                         : test::source_dir() / object;
  Session session = capture_sim(dir / "scan",
                                "sim:synthetic?mesh=" + mesh.string() +
                                    "&noise=0.0005&dropout=0.01&color_noise=2&width=320&height=240&distance=0.45"
                                    "&elevation_deg=20&fov_deg=50&center=1&seed=1" + extra,
                                views);
  m = session.manifest();
  return views_of(session);
}

// A sparse scan of a small near-symmetric object (the bundled Rubik's cube at
// 320x240 from 0.45 m: 1.4 mm between points, its faces alike but for their
// stickers) with two angles off by +12 and -18 deg. Before, every ICP pair read
// as no overlap (the final distance, 0.4 % of the session, was a third of the
// point spacing: fitness 0.12), so clean angles were taken unchecked; with that
// fixed, the free-space check refused even the right pose of a view (a third of
// its points "seen through" at other views' silhouettes and grazing faces), the
// two views failed, and the run without angles, its views 90-180 deg off on the
// cube's turned twins, was kept: exit 0, 12 of 12, 180 deg off.
TEST(SimRegistration, WrongAnglesOnASparseCubeAreFoundByColour) {
  test::TempDir dir;
  SessionManifest m;
  const std::vector<Cloud> clouds = sparse_scan(dir, "rubiks_cube", 12, m);
  ASSERT_EQ(clouds.size(), 12u);
  *m.views[3].angle_deg += 12;
  *m.views[8].angle_deg -= 18;
  const RegistrationResult r = register_views(clouds, m);
  print_prior("a sparse cube, two angles off", r);
  expect_all_within_targets(r, 12);
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    ASSERT_TRUE(r.views[i].angle_error_deg.has_value()) << i;
    const double e = std::abs(*r.views[i].angle_error_deg);
    if (i == 3 || i == 8) EXPECT_GT(e, 10.0) << i;
    else EXPECT_LT(e, 1.0) << i;
    EXPECT_EQ(r.views[i].prior, i == 3 || i == 8 ? PriorUse::kRejected : PriorUse::kUsed) << i;
  }
}

// The same cube without any angle, and with its angle list of the wrong sign:
// the views are chained by global registration of each to the one or two before,
// by shape alone, and the shape of a cube fits its turned twins as well (all six
// RANSAC poses of the first pair landed 105 deg off, colours 114 apart per
// channel): every view but the first came out 90-180 deg off, exit 0. A chain's
// pair now weighs colour: a pose whose colours disagree gives way to the
// multi-start until one agrees, and where none does the view is tried against
// the view before that one rather than taken at once.
TEST(SimRegistration, ASparseCubeWithoutAnglesIsChainedByColour) {
  test::TempDir dir;
  SessionManifest clean;
  const std::vector<Cloud> clouds = sparse_scan(dir, "rubiks_cube", 12, clean);
  ASSERT_EQ(clouds.size(), 12u);
  SessionManifest bare = clean, flipped = clean;
  bare.axis.reset();
  for (ViewRecord& v : bare.views) v.angle_deg.reset();
  for (ViewRecord& v : flipped.views) v.angle_deg = -*v.angle_deg;
  for (const auto& [what, m] : {std::pair<const char*, const SessionManifest*>{"no angles", &bare},
                                {"angles of the wrong sign", &flipped}}) {
    const RegistrationResult r = register_views(clouds, *m);
    print_prior(what, r);
    expect_all_within_targets(r, 12, what);
  }
}

// Eight views of the bottle with angles of the wrong sign: the run as given held
// half of its views by the angles alone (their pairs failed), 0.342 mm over the
// pairs that converged; the corrected run joined all eight at 0.344 mm, not 5 %
// better, so the run as given was kept with four views 90-180 deg off, exit 0.
// The corrected run now wins by joining more views by pairs.
TEST(SimRegistration, AWrongSignIsCorrectedWhereTheRunAsGivenHoldsViewsByItsAnglesAlone) {
  test::TempDir dir;
  SessionManifest m;
  const std::vector<Cloud> clouds = sparse_scan(dir, "mustard_bottle", 8, m);
  ASSERT_EQ(clouds.size(), 8u);
  for (ViewRecord& v : m.views) v.angle_deg = -*v.angle_deg;
  const RegistrationResult r = register_views(clouds, m);
  print_prior("the bottle, 8 views, angles of the wrong sign", r);
  EXPECT_EQ(r.prior_kept, "corrected prior");
  expect_all_within_targets(r, 8);
  EXPECT_EQ(r.unlinked_views, 0);
}

// The fandisk (no colours) in eight views with angles of the wrong sign, and with
// step indices for degrees: the run as given registered 4 (2) of 8, and the run
// without angles, which judges the angles, chained five views onto a turned
// placement 99 deg off (a near-symmetric part seen 45 deg apart), so the angles fit
// it nowhere and it was kept, exit 0. Now the conventions are tried as hypotheses
// where that fit fails: the opposite sign (steps of 45 degrees) registers all eight,
// joined by pairs, and is kept as the corrected prior.
//
// (The simulated part is grey, one colour: the colour-gated feature matches, which
// only need colours to agree, placed the run without angles right since the
// twenty-sixth session, so the hypotheses were no longer needed here. They are
// switched off, colour_gate = 0, to keep the run without angles wrong as it was;
// with them the three sessions come out right too, last below.)
TEST(SimRegistration, AConventionMistakeIsFoundWhereTheRunWithoutAnglesIsWrongToo) {
  test::TempDir dir;
  SessionManifest clean;
  const std::vector<Cloud> clouds =
      sparse_scan(dir, "tests/data/consolidation/fandisk.off", 8, clean, "&scale=0.18");
  ASSERT_EQ(clouds.size(), 8u);
  SessionManifest flipped = clean, steps = clean;
  for (ViewRecord& v : flipped.views) v.angle_deg = -*v.angle_deg;
  for (std::size_t i = 0; i < steps.views.size(); ++i) steps.views[i].angle_deg = double(i);
  RegistrationParams ungated;
  ungated.global.colour_gate = 0;
  for (const auto& [what, m, convention] :
       {std::tuple<const char*, const SessionManifest*, const char*>{"the wrong sign", &flipped, "the opposite sign"},
        {"step indices", &steps, "steps of 45 degrees"}}) {
    const RegistrationResult r = register_views(clouds, *m, ungated);
    print_prior(what, r);
    EXPECT_EQ(r.prior_kept, "corrected prior") << what;
    expect_all_within_targets(r, 8, what);
    bool said = false;
    for (const std::string& w : r.warnings)
      said = said || (w.find(convention) != std::string::npos && w.find("tried as a hypothesis") != std::string::npos);
    EXPECT_TRUE(said) << what;
    for (std::size_t i = 0; i < r.views.size(); ++i) EXPECT_EQ(r.views[i].prior, PriorUse::kCorrected) << what << i;
  }
  // The wrong sign and one angle 20 deg off besides: that view registers without its
  // angle, and its warning quotes the angle the user gave (before, the corrected
  // run's "commanded angle 245 deg" where the user wrote -245).
  SessionManifest also = flipped;
  *also.views[5].angle_deg -= 20;
  const RegistrationResult r = register_views(clouds, also, ungated);
  print_prior("the wrong sign and one angle off", r);
  EXPECT_EQ(r.prior_kept, "corrected prior");
  expect_all_within_targets(r, 8);
  for (std::size_t i = 0; i < r.views.size(); ++i)
    EXPECT_EQ(r.views[i].prior, i == 5 ? PriorUse::kRejected : PriorUse::kCorrected) << i;
  bool quoted = false;
  for (const std::string& w : r.warnings)
    quoted = quoted || w.find("commanded angle -245 deg (245 corrected) looks wrong") != std::string::npos;
  EXPECT_TRUE(quoted);
  // With the colour-gated matches (the default): every session right as well.
  for (const auto& [what, m] : {std::pair<const char*, const SessionManifest*>{"the wrong sign, gated", &flipped},
                                {"step indices, gated", &steps},
                                {"the wrong sign and one angle off, gated", &also}}) {
    const RegistrationResult g = register_views(clouds, *m);
    print_prior(what, g);
    expect_all_within_targets(g, 8, what);
  }
}

// The views of `clean` / `clouds` in the list order `order` (a session given out of
// turntable order), with the angles 0, 30, 60, ... in that list order, or none.
void in_list_order(const SessionManifest& clean, const std::vector<Cloud>& clouds,
                   const std::vector<std::size_t>& order, bool angles, SessionManifest& m,
                   std::vector<Cloud>& shuffled) {
  m = clean;
  m.views.clear();
  shuffled.clear();
  for (std::size_t k = 0; k < order.size(); ++k) {
    m.views.push_back(clean.views[order[k]]);
    shuffled.push_back(clouds[order[k]]);
    if (angles) m.views.back().angle_deg = 30.0 * double(k);
    else m.views.back().angle_deg.reset();
  }
}

// Views given out of turntable order (a shell glob, files renamed): the bottle's
// twelve views shuffled, their angles 0, 30, ... in the new order, and the
// fandisk's twelve shuffled without any angle. The run without angles chained each
// view to the one before it in the list, often far round the object, and joined
// four of the bottle's front views onto its back (the half-turned twin, 179 deg
// off, exit 0); the fandisk's chain put views on twins and failed two. Most views
// keep to one turntable line (registration/axis_consensus.h); the others are now
// placed again about it, never where a kept view already is, and the ring refined
// in the order of the turns.
TEST(SimRegistration, ViewsOutOfTurntableOrderArePlacedAboutTheAxisMostViewsShare) {
  const std::vector<std::size_t> order = {7, 11, 3, 10, 8, 4, 9, 1, 0, 6, 2, 5};
  for (const bool bottle : {true, false}) {
    test::TempDir dir;
    SessionManifest clean;
    const std::vector<Cloud> clouds =
        bottle ? sparse_scan(dir, "mustard_bottle", 12, clean)
               : sparse_scan(dir, "tests/data/consolidation/fandisk.off", 12, clean, "&scale=0.18");
    ASSERT_EQ(clouds.size(), 12u);
    SessionManifest m;
    std::vector<Cloud> shuffled;
    in_list_order(clean, clouds, order, bottle, m, shuffled);
    if (!bottle) m.axis.reset();
    const char* what = bottle ? "the bottle shuffled, angles in list order" : "the fandisk shuffled, no angles";
    const RegistrationResult r = register_views(shuffled, m);
    print_prior(what, r);
    expect_all_within_targets(r, 12, what);
    bool said = false;
    for (const std::string& n : r.notes) said = said || n.find("placed again about the turntable axis") != std::string::npos;
    EXPECT_TRUE(said) << what;
  }
}

// The Rubik's cube in 12 views at 640x480, given out of turntable order with the
// angles 0, 30, ... in list order (the session's calibrated axis kept). The run without
// angles chained each view to the one before it in the list, on the cube's turned
// twins (a cube on a turntable fits its quarter turns by shape alone), and stacked the
// views on two turns of a line 63 deg off the table's: no line held three distinct
// turns, so nothing was placed again, exit 0, 180 deg off. With a calibrated axis the
// line is known: the views are placed about it from the first one on, where their
// colours agree with the views placed before them (a twin reads 33-137 per channel
// there, a right pose 4-6).
TEST(SimRegistration, ACubeOutOfTurntableOrderIsPlacedAboutTheCalibratedAxisByColour) {
  const std::vector<std::size_t> order = {7, 11, 3, 10, 8, 4, 9, 1, 0, 6, 2, 5};
  test::TempDir dir;
  Session session = capture_sim(dir / "scan",
                                "sim:synthetic?mesh=" + (test::source_dir() / "data" / "rubiks_cube" / "textured.obj").string() +
                                    "&noise=0.0005&dropout=0.01&color_noise=2&width=640&height=480&distance=0.45"
                                    "&elevation_deg=20&fov_deg=50&center=1&seed=1",
                                12);
  const SessionManifest clean = session.manifest();
  const std::vector<Cloud> clouds = views_of(session);
  ASSERT_EQ(clouds.size(), 12u);
  ASSERT_TRUE(clean.axis.has_value());
  SessionManifest m;
  std::vector<Cloud> shuffled;
  in_list_order(clean, clouds, order, true, m, shuffled);
  // (Since the twenty-sixth session the run without angles matches the features where
  // their colours agree when every pose found brings different colours together,
  // and places all twelve right by itself: 0.10 deg. The gate is switched off here to
  // keep the placement about the calibrated axis tested.)
  RegistrationParams ungated;
  ungated.global.colour_gate = 0;
  const RegistrationResult r = register_views(shuffled, m, ungated);
  print_prior("the cube at 640x480 shuffled, angles in list order", r);
  expect_all_within_targets(r, 12, "the cube at 640x480 shuffled");
  bool said = false;
  for (const std::string& n : r.notes)
    said = said || n.find("placed again about the session's calibrated turntable axis") != std::string::npos;
  EXPECT_TRUE(said);
}

// The fandisk in 24 views with step indices 0, 1, ..., 23 for its angles: the run as
// given (its wrong angles pulling in the pose graph) converged every pair but bent
// half the ring 2.5 deg / 26 mm off and refused one rigid turntable, and was kept
// over the corrected run (0.395 against 0.397 mm: not 5 % worse), exit 0. Where the
// angles fit only under a convention, every angle as given is wrong: the corrected
// run is now kept unless the run as given registers or joins more, or fits clearly
// better.
TEST(SimRegistration, StepIndicesOverAFullRingKeepTheCorrectedRun) {
  test::TempDir dir;
  SessionManifest m;
  const std::vector<Cloud> clouds = sparse_scan(dir, "tests/data/consolidation/fandisk.off", 24, m, "&scale=0.18");
  ASSERT_EQ(clouds.size(), 24u);
  for (std::size_t i = 0; i < m.views.size(); ++i) m.views[i].angle_deg = double(i);
  const RegistrationResult r = register_views(clouds, m);
  print_prior("the fandisk, 24 views, step indices", r);
  EXPECT_EQ(r.prior_kept, "corrected prior");
  expect_all_within_targets(r, 24);
}

// The bottle's eight views with three angles off (+5, +10 and -20 deg on views 1, 2
// and 5; a campaign's case): the -20 is found and dropped, but +5 and +10 (the
// latter under the wrong-angle check after the prior check's consensus) stayed in
// the pose graph, whose few converging pairs 45 deg apart could not hold against
// them: four views 0.74 deg off (one angle 6 deg off alone: 0.49 deg). A prior edge
// the solved graph turns more than two sigmas from is now dropped where converged
// pairs hold both its views.
TEST(SimRegistration, AnglesAFewDegreesOffDoNotPullASparseRing) {
  test::TempDir dir;
  SessionManifest m;
  const std::vector<Cloud> clouds = sparse_scan(dir, "mustard_bottle", 8, m);
  ASSERT_EQ(clouds.size(), 8u);
  SessionManifest one = m;
  *one.views[2].angle_deg += 6;
  *m.views[1].angle_deg += 5;
  *m.views[2].angle_deg += 10;
  *m.views[5].angle_deg -= 20;
  for (const auto& [what, manifest] : {std::pair<const char*, const SessionManifest*>{"three angles off", &m},
                                       {"one angle 6 deg off", &one}}) {
    const RegistrationResult r = register_views(clouds, *manifest);
    print_prior(what, r);
    expect_all_within_targets(r, 8, what);
    EXPECT_LT(r.max_rotation_error_deg, 0.3) << what;
  }
}

// The fandisk's eight views with the first four recorded without angle (half a
// turn; a campaign's case): each was registered against the model of the four
// posed views alone, and the third, 90 deg from the nearest of them, overlapped it
// too little where it belongs and fitted its half-turned twin: 178 deg off, exit 0,
// no warning. The table views without angle now go nearest a posed view first, each
// placed near its expected turn joining the model for the next.
TEST(SimRegistration, TableViewsWithoutAngleArePlacedFromTheNearestPosedViewOnAndHeldOnTheLine) {
  test::TempDir dir;
  SessionManifest m;
  const std::vector<Cloud> clouds = sparse_scan(dir, "tests/data/consolidation/fandisk.off", 8, m, "&scale=0.18");
  ASSERT_EQ(clouds.size(), 8u);
  SessionManifest scattered = m;
  for (int i : {0, 1, 2, 3}) m.views[std::size_t(i)].angle_deg.reset();
  const RegistrationResult r = register_views(clouds, m);
  print_prior("the fandisk, views 0-3 without angle", r);
  expect_all_within_targets(r, 8);
  // Views 1, 3 and 6 without angle: view 6, between posed views 90 deg apart, slid
  // 1.07 mm where its two pairs barely hold it. A table view without angle placed
  // near its expected pose and on the table's line is now held on the line by the
  // rigid solve, with an angle of its own.
  for (int i : {1, 3, 6}) scattered.views[std::size_t(i)].angle_deg.reset();
  const RegistrationResult s = register_views(clouds, scattered);
  print_prior("the fandisk, views 1, 3, 6 without angle", s);
  expect_all_within_targets(s, 8);
  EXPECT_TRUE(s.rigid_turntable);
}

// A second pass with the object turned over (issue 26, item 2): after view 5
// the blocks lie upside down on the table (half a turn about the object's x,
// lifted back onto the table top). Before, the second run was placed from the
// angles and came out 180 deg / 77 mm off; now it is registered onto the first
// as a whole (global registration of the two merged runs), then refined: every
// view within 0.5 deg / 1 mm of the truth at the object.
TEST(SimRegistration, ASecondPassTurnedOverIsRegisteredAsTwoTurntableRuns) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  ASSERT_TRUE(c.m.axis.has_value());
  Eigen::Matrix4d D = Eigen::Matrix4d::Identity();
  D.block<3, 3>(0, 0) = Eigen::AngleAxisd(M_PI, Vec3d::UnitX()).toRotationMatrix();  // object frame: z up
  D.block<3, 1>(0, 3) = Vec3d(0.01, 0, 0.14);  // the blocks are 0.14 high
  c.move_object(D, 6, 11);
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("object turned over after view 5", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  bool named = false;
  for (const std::string& w : r.warnings)
    named = named || w.find("views from views[6] (view_006.ply) on were registered to the ones before") != std::string::npos;
  EXPECT_TRUE(named);
  // The second run's angles are off by the turn together, not mis-commanded: each
  // run's angles are fitted alone (before, views 6-11 were each named 29-179 deg off).
  expect_no_angle_named_wrong(r);
}


// One view's object shifted 3 cm on the table (bumped for that view, put back
// after it): its prior pose is wrong by the shift, not by its angle. Found by
// the data, registered without its prior, every view within 0.5 deg / 1 mm.
TEST(SimRegistration, OneViewWithTheObjectShiftedIsRegisteredWithoutItsPrior) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  Eigen::Matrix4d D = Eigen::Matrix4d::Identity();
  D.block<3, 1>(0, 3) = Vec3d(0.025, -0.015, 0);  // object frame: z up; 2.9 cm across the table
  const std::size_t i = 4;
  c.move_object(D, i, i);
  const RegistrationResult r = register_views(c.clouds, c.m);
  print_prior("view 4's object shifted 3 cm", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
  EXPECT_NE(r.views[i].prior, PriorUse::kUsed);
}

// Ten of the twelve views of `c` as the issue's session has them: six with nominal
// angles (0, 60, 90, 191, 270, 300; the truth is i * 30, view 6 truly 180) and
// four without.
void as_the_issues_session(const PriorCase& c, std::vector<Cloud>& clouds, SessionManifest& m) {
  m = c.m;
  m.views.clear();
  clouds.clear();
  const std::vector<std::pair<int, double>> keep = {
      {0, 0}, {1, -1}, {2, 60}, {3, 90}, {4, -1}, {6, 191}, {7, -1}, {9, 270}, {10, 300}, {11, -1}};
  for (const auto& [i, nominal] : keep) {
    ViewRecord v = c.m.views[std::size_t(i)];
    if (nominal < 0) v.angle_deg.reset();
    else v.angle_deg = nominal;
    m.views.push_back(v);
    clouds.push_back(c.clouds[std::size_t(i)]);
  }
}

// The issue's own session, simulated with known truth: six table views with
// nominal angles (0, 60, 90, 180, 270, 300; one of them really 11 degrees
// off), the object moved 5 cm and turned between two of them, and four views
// with no angle (two before the move, two after). Every view registered within
// 0.5 deg / 1 mm at the object of the truth (object frame: before the move).
TEST(SimRegistration, TheIssuesSessionNominalAnglesAMoveAndViewsWithoutAngle) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  const Eigen::Matrix4d D = table_move(10, Vec3d(0.04, 0.03, 0));
  c.move_object(D, 5, 11);  // moved after view 4
  std::vector<Cloud> clouds;
  SessionManifest m;
  as_the_issues_session(c, clouds, m);
  const RegistrationResult r = register_views(clouds, m);
  print_prior("the issue's session", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.views_with_reference, 10);
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
}

// The same session with the object turned on the table and the views after the
// move scanned again with it there (`rescan_moved`: the scanner sees the sides the
// turn brought round). Before the free-space rule: 10 deg and 5 cm came out with two
// views 62 deg off, 135 deg with two 174 deg off, each with exit 0, every view
// registered and joined by pairs (weak ones, on the fandisk's near twins). The runs
// kept put those views where the other views saw through (21-29 % of a view); a run
// whose views agree with what all the others saw (at most 10 %) is kept instead.
// With 45 deg no run places every view right: the one kept registers seven, right
// (the run without angles placed all ten, five of them half turned, 58 % of a view
// seen through); the three it could not place start where another run placed them
// clear of what its views saw, and all ten are registered right. With -30 deg the
// run without angles placed one view 63 deg off, 10 % of it seen through but up to
// 16 % of the right views it contradicts (kRunSeenThrough, 15 %): the run with the
// corrected angles was kept, six views right and four named; since a view whose angle
// looks wrong is kept off the half-turned twin near its angle (check_angles'
// kSuspectNearDeg), the run with the angles places all ten right. With 90 deg every run had
// the same two views 170 deg off (15-18 % seen through, the others 0-1 %): they are
// taken out and named, the other eight registered right.
TEST(SimRegistration, TheIssuesSessionWithTheObjectTurnedAndScannedAgain) {
  struct Move {
    double deg;
    Vec3d shift;
    std::size_t failed;
  };
  for (const Move& mv : {Move{10, Vec3d(0.04, 0.03, 0), 0}, Move{135, Vec3d(0, 0.05, 0), 0},
                         Move{45, Vec3d(0.03, 0.02, 0), 0}, Move{-30, Vec3d(0.02, 0.04, 0), 0},
                         Move{90, Vec3d(0.05, 0, 0), 2}}) {
    PriorCase c;
    ASSERT_EQ(c.clouds.size(), 12u);
    c.rescan_moved(table_move(mv.deg, mv.shift), 5, 11);  // moved after view 4
    std::vector<Cloud> clouds;
    SessionManifest m;
    as_the_issues_session(c, clouds, m);
    const RegistrationResult r = register_views(clouds, m);
    const std::string what = "turned " + std::to_string(int(mv.deg)) + " deg";
    print_prior(what.c_str(), r);
    EXPECT_EQ(r.failed_views.size(), mv.failed) << what;
    EXPECT_EQ(r.views_with_reference, int(10 - mv.failed)) << what;
    EXPECT_LT(r.max_rotation_error_deg, 0.5) << what;
    EXPECT_LT(r.max_object_translation_error, 0.001) << what;
    for (std::size_t i = 0; i < r.views.size(); ++i) {
      if (!r.views[i].registered) {
        EXPECT_FALSE(r.views[i].message.empty()) << what << ": view " << i;
        if (mv.deg == 90) {
          EXPECT_NE(r.views[i].message.find("where the other views saw through"), std::string::npos)
              << r.views[i].message;
        }
        continue;
      }
      ASSERT_TRUE(r.views[i].seen_through.has_value()) << what << ": view " << i;
      EXPECT_LE(*r.views[i].seen_through, 0.1) << what << ": view " << i;
    }
  }
}


// The issue's session (the views and nominal angles of as_the_issues_session: one
// angle 11 degrees off, four views without angle) of an everyday near-symmetric
// object from data/ (a textured model: the mustard bottle looks alike from its front
// and back, the Rubik's cube from each side), scanned with or without colours. With
// `deg` or `shift`, the object turned by `deg` about its up and slid by `shift`
// (metres) after view 4, and views 5-11 scanned again with it there; the truth in the
// frame of the object before the move.
struct EverydaySession {
  std::vector<Cloud> clouds;
  SessionManifest m;
};
EverydaySession everyday_issue_session(const test::TempDir& dir, const std::string& model, bool colour,
                                       double deg = 0, const Vec3d& shift = Vec3d::Zero()) {
  const std::filesystem::path obj = test::source_dir() / "data" / model / "textured.obj";
  const std::string options = "&noise=0.0005&seed=1&dropout=0.01&width=320&height=240" +
                              std::string(colour ? "&color_noise=2" : "&color=0");
  Session before = capture_sim(dir / "before", "sim:synthetic?mesh=" + obj.string() + options + "&center=1", 12);
  SessionManifest m = before.manifest();
  std::vector<Cloud> all;
  for (std::size_t i = 0; i < m.views.size(); ++i) all.push_back(before.load_view(i));
  if (deg != 0 || shift != Vec3d::Zero()) {
    // The model turned and slid where the simulator placed it (center=1: its box
    // centred on the table's axis, standing on the table: `off`), written out as is
    // (center=0). The poses' object frame is the model's own, so a moved view's truth
    // is M = T(-off) R^-1 T(-shift) times its pose. (Vertex normals are left as they
    // are: the simulator does not read them.)
    std::ifstream in(obj);
    std::vector<std::string> lines;
    Aabb box;
    for (std::string line; std::getline(in, line);) {
      lines.push_back(line);
      if (line.rfind("v ", 0) == 0) {
        std::istringstream v(line.substr(2));
        Vec3f p;
        v >> p.x() >> p.y() >> p.z();
        box.extend(p);
      }
    }
    const Vec3d off(-0.5 * (box.min.x() + box.max.x()), -0.5 * (box.min.y() + box.max.y()), -box.min.z());
    const Eigen::Matrix3d R = Eigen::AngleAxisd(deg * M_PI / 180, Vec3d::UnitZ()).toRotationMatrix();
    std::ofstream out(dir / "moved.obj");
    for (const std::string& line : lines) {
      if (line.rfind("v ", 0) == 0) {
        std::istringstream v(line.substr(2));
        Vec3d p;
        v >> p.x() >> p.y() >> p.z();
        const Vec3d q = R * (p + off) + shift;
        out << "v " << std::setprecision(9) << q.x() << ' ' << q.y() << ' ' << q.z() << '\n';
      } else if (line.rfind("mtllib ", 0) == 0) {
        out << "mtllib " << (obj.parent_path() / line.substr(7)).string() << '\n';
      } else {
        out << line << '\n';
      }
    }
    out.close();
    Session after = capture_sim(dir / "after", "sim:synthetic?mesh=" + (dir / "moved.obj").string() + options + "&center=0", 12);
    Eigen::Matrix4d M = Eigen::Matrix4d::Identity();
    M.block<3, 3>(0, 0) = R.transpose();
    M.block<3, 1>(0, 3) = -R.transpose() * shift - off;
    for (std::size_t i = 5; i < m.views.size(); ++i) {
      all[i] = after.load_view(i);
      m.views[i].reference_pose = M * *after.manifest().views[i].reference_pose;
    }
  }
  EverydaySession out;
  out.m = m;
  out.m.views.clear();
  const std::vector<std::pair<int, double>> keep = {
      {0, 0}, {1, -1}, {2, 60}, {3, 90}, {4, -1}, {6, 191}, {7, -1}, {9, 270}, {10, 300}, {11, -1}};
  for (const auto& [i, nominal] : keep) {
    ViewRecord v = m.views[std::size_t(i)];
    if (nominal < 0) v.angle_deg.reset();
    else v.angle_deg = nominal;
    out.m.views.push_back(v);
    out.clouds.push_back(all[std::size_t(i)]);
  }
  return out;
}

// Before: the bottle without colours had the view 11 degrees off and the view without
// angle after it 179 degrees off (the angle found wrong, global registration took the
// half-turned twin, and the view after it, its neighbours with angles 180 degrees
// apart over four steps, expected nowhere, followed); with colours too. The coloured
// Rubik's cube had four views 180 degrees off: the run without angles placed views on
// twins, the opposite sign fitted 3 of its 6 angles, and the run with the opposite
// sign was kept. All within 0.5 deg / 1 mm of the truth now. (Knocked on the table
// and scanned again, these objects still come out with views on twins:
// docs/registration.md, "Near-symmetric everyday objects".)
TEST(SimRegistration, TheIssuesSessionOfEverydayNearSymmetricObjects) {
  struct Case {
    const char* model;
    bool colour;
  };
  for (const Case& c : {Case{"mustard_bottle", false}, Case{"mustard_bottle", true}, Case{"rubiks_cube", true}}) {
    test::TempDir dir;
    const EverydaySession s = everyday_issue_session(dir, c.model, c.colour);
    const RegistrationResult r = register_views(s.clouds, s.m);
    const std::string what = std::string(c.model) + (c.colour ? ", colours" : ", no colours");
    print_prior(what.c_str(), r);
    EXPECT_TRUE(r.failed_views.empty()) << what;
    EXPECT_EQ(r.views_with_reference, 10) << what;
    EXPECT_LT(r.max_rotation_error_deg, 0.5) << what;
    EXPECT_LT(r.max_object_translation_error, 0.001) << what;
  }
}

// The bottle without colours knocked on the table after view 4 and scanned again: the
// views after the knock, registered to the others as a whole, fit them turned by half
// a turn too, and nothing in the scans tells the two places apart (the knock's size
// is unknown). Where they land on the turned one (before: 179.6 and 179.7 deg off,
// exit 0, no word of it), a warning must say their place may be the turned one.
// Knocked 90 deg, the run kept is the one with the angles corrected by the moved
// views' shared error, which no placement as a whole checked: the first view after the
// knock (its angle found wrong) and the view without angle before it 179.9 deg off,
// not named before the twenty-fifth session; now the view without angle is named
// (settle_view_twins; two views in their right places with it).
//
// The coloured bottle knocked 45 deg: the run without angles is kept; it had the views
// after the knock on the twin (179.4 deg off), its run after the move is now turned by
// the colours (AKnockedColouredBottleIsPlacedWhereItsColoursSay); here: right, or named.
// (Before this session the run with the angles was kept, its group on the twin, named.)
TEST(SimRegistration, AKnockedNearSymmetricBottleIsNeverPlacedTurnedWithoutAWord) {
  int turned = 0;
  for (const auto& [deg, colour] : {std::pair{-30.0, false}, {45.0, false}, {90.0, false}, {45.0, true}}) {
    test::TempDir dir;
    const EverydaySession s = everyday_issue_session(dir, "mustard_bottle", colour, deg, Vec3d(0.03, 0.02, 0));
    const RegistrationResult r = register_views(s.clouds, s.m);
    const std::string what = std::string(colour ? "coloured " : "") + "bottle knocked " + std::to_string(int(deg)) + " deg";
    print_prior(what.c_str(), r);
    bool warned = false;
    for (const std::string& w : r.warnings)
      warned = warned || w.find("place may be the turned one") != std::string::npos;
    // The registered views (views failed by name are no silent error).
    const bool off = r.max_rotation_error_deg >= 0.5 || r.max_object_translation_error >= 0.001;
    turned += r.max_rotation_error_deg > 90 ? 1 : 0;
    EXPECT_TRUE(!off || warned) << what << ": " << r.max_rotation_error_deg << " deg off, no warning";
  }
  // The case the warning is for does occur here (views placed turned: a session where
  // every knock lands right would not test it).
  EXPECT_GT(turned, 0);
}

// An everyday session (10 views) registered whole, each view within 0.5 deg / 1 mm at
// the object, and a warning or note saying the colours chose a place.
void expect_everyday_right_and_colours_said(const RegistrationResult& r, const std::string& what) {
  print_prior(what.c_str(), r);
  EXPECT_TRUE(r.failed_views.empty()) << what;
  EXPECT_EQ(r.views_with_reference, 10) << what;
  EXPECT_LT(r.max_rotation_error_deg, 0.5) << what;
  EXPECT_LT(r.max_object_translation_error, 0.001) << what;
  bool said = false;
  for (const auto* words : {&r.warnings, &r.notes})
    for (const std::string& w : *words)
      said = said || w.find("the colours chose between the two") != std::string::npos ||
             w.find("the colours favour that place") != std::string::npos;
  EXPECT_TRUE(said) << what;
}

// The bottle with colours, knocked on the table after view 4 and scanned again. Its
// front and back differ in print, so its colours tell its place where the shapes fit
// both: knocked -30 deg, the views after the knock were registered to the others as a
// whole on the half-turned twin (the colours favouring the turned place 7.5 against
// 25.8); knocked 10 deg, the first view after the knock (its angle found wrong) and the
// view without angle after it were placed on their twins by global registration (the
// shapes: overlap 1.0 there against 0.70 in the right place; colours 8.7 at the
// turned place against 16.4).
// Knocked 45 and 90 deg, the run without angles is kept (it registers more views), with
// the views after the knock on the twin: its run after the move is checked the same way
// (settle_runs_twin). Before: 179.7, 179.8, 179.9 and 179.8 deg off. Now each view
// within 0.5 deg / 1 mm, and said.
TEST(SimRegistration, AKnockedColouredBottleIsPlacedWhereItsColoursSay) {
  for (const double deg : {-30.0, 10.0, 45.0, 90.0}) {
    test::TempDir dir;
    const EverydaySession s = everyday_issue_session(dir, "mustard_bottle", true, deg, Vec3d(0.03, 0.02, 0));
    const RegistrationResult r = register_views(s.clouds, s.m);
    const std::string what = "coloured bottle knocked " + std::to_string(int(deg)) + " deg";
    // (Knocked 90 deg, since the colour-gated matches the run without angles has placed
    // the views right by their colours, said in a note.)
    expect_everyday_right_and_colours_said(r, what);
  }
}

// The Rubik's cube with colours: its shape looks alike turned by a quarter, so the
// shapes' features match every face to every other and global registration's best
// pose lands on a turned twin whose colours differ everywhere (55-135 per channel
// against 5-6 for right pairs). Without any angle the chain placed views 90-120 deg
// off (the cube unknocked: 119.9 deg); knocked after view 4 by 10, 90 or 135 deg (with
// the angles) 89.9-180 deg off, not named. The features are now matched where their
// colours agree as well where the pose found brings different colours together (or
// none was found), and of two chains the one with fewer pairs whose colours refute
// them is kept; the notes say where the colours chose. Each view within
// 0.5 deg / 1 mm, and no pair named for its colours.
TEST(SimRegistration, AColouredCubeIsPlacedByItsColoursWhereItsShapeLooksAlikeTurned) {
  struct Case {
    double deg;
    bool angles;
  };
  for (const Case& c : {Case{0, false}, Case{10, true}, Case{90, true}, Case{135, true}}) {
    test::TempDir dir;
    EverydaySession s = everyday_issue_session(dir, "rubiks_cube", true, c.deg,
                                               c.deg == 0 ? Vec3d::Zero() : Vec3d(0.03, 0.02, 0));
    if (!c.angles)
      for (ViewRecord& v : s.m.views) v.angle_deg.reset();
    const RegistrationResult r = register_views(s.clouds, s.m);
    const std::string what = "coloured cube knocked " + std::to_string(int(c.deg)) + " deg" +
                             (c.angles ? "" : ", no angles");
    expect_everyday_right_and_colours_said(r, what);
    for (const std::string& w : r.warnings) EXPECT_EQ(w.find("overlap where their colours differ"), std::string::npos) << what;
  }
  // Knocked -30 and 45 deg: still off (179.9 / 179.6 deg, silent before); named now by
  // the pairs that overlap where their colours differ.
  for (const double deg : {-30.0, 45.0}) {
    test::TempDir dir;
    const EverydaySession s = everyday_issue_session(dir, "rubiks_cube", true, deg, Vec3d(0.03, 0.02, 0));
    const RegistrationResult r = register_views(s.clouds, s.m);
    const std::string what = "coloured cube knocked " + std::to_string(int(deg)) + " deg";
    print_prior(what.c_str(), r);
    bool named = false;
    for (const std::string& w : r.warnings) named = named || w.find("overlap where their colours differ") != std::string::npos;
    EXPECT_TRUE(named || (r.max_rotation_error_deg < 0.5 && r.max_object_translation_error < 0.001)) << what;
  }
}

// Two runs of views with a gap of 120 degrees between them on both sides
// (views 0-2 and 6-8 of the fandisk session): no pair joins the runs, so their
// place relative to each other rests on the angles alone. Registered, and said
// so, naming the group.
TEST(SimRegistration, ViewsThatNoPairJoinsAreNamed) {
  PriorCase c;
  ASSERT_EQ(c.clouds.size(), 12u);
  SessionManifest m = c.m;
  m.views.clear();
  std::vector<Cloud> clouds;
  for (int i : {0, 1, 2, 6, 7, 8}) {
    m.views.push_back(c.m.views[std::size_t(i)]);
    clouds.push_back(c.clouds[std::size_t(i)]);
  }
  const RegistrationResult r = register_views(clouds, m);
  print_prior("two runs 120 degrees apart", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_EQ(r.unlinked_views, 3);
  // A gap in the coverage is not taken for a move: the run without angles joins
  // no more views across it, so the prior's run is kept.
  EXPECT_EQ(r.prior_kept, "prior");
  bool named = false;
  for (const std::string& w : r.warnings)
    named = named || w.find("views[3] (view_006.ply), views[4] (view_007.ply) and views[5] (view_008.ply) (3 views) "
                            "overlap none of the other views: held to them by the turntable angles alone") !=
                         std::string::npos;
  EXPECT_TRUE(named);
  // The clean session: every view joined.
  const RegistrationResult all = register_views(c.clouds, c.m);
  EXPECT_EQ(all.unlinked_views, 0);
}

}  // namespace
}  // namespace station

namespace station {
namespace {

// Issue 26, item 3: views taken off the table (two from above, two from low
// down; no angle) of the bundled mustard bottle, a coloured shape that looks
// alike from its front and its back. With one RANSAC run's six hypotheses
// refined, the low view at 135 degrees came out turned half way about the
// bottle's own vertical axis (179.8 deg, 45 mm at the object; on the same case
// at full resolution the wrong pose fits 0.968 against the right one's 0.974,
// and its colours are 33 against 9 apart); the more starts and the colour
// check register every one.
TEST(SimRegistration, OffTableViewsOfANearSymmetricObjectRegister) {
  test::TempDir dir("station-offtable");
  const std::string mesh = (test::source_dir() / "data" / "mustard_bottle" / "textured.obj").string();
  std::vector<Cloud> clouds;
  SessionManifest m;
  const auto scan = [&](const std::string& name, double elevation, int views, double start, bool angles) {
    // The off-table views at full resolution: from above the bottle is its cap.
    const std::string size = angles ? "&width=320&height=240" : "&width=640&height=480";
    Session s = capture_sim(dir / name,
                            "sim:synthetic?mesh=" + mesh + "&noise=0.0005&seed=5" + size +
                                "&elevation_deg=" + std::to_string(elevation),
                            views, start);
    if (!angles) {
      for (std::size_t i = 0; i < s.manifest().views.size(); ++i) {
        ViewRecord v = s.manifest().views[i];
        v.angle_deg.reset();
        m.views.push_back(v);
        clouds.push_back(s.load_view(i));
      }
      return;
    }
    m = s.manifest();
    for (std::size_t i = 0; i < m.views.size(); ++i) clouds.push_back(s.load_view(i));
  };
  scan("table", 20, 8, 0, true);
  scan("top", 70, 2, 0, false);
  scan("low", -10, 2, 135, false);
  ASSERT_EQ(clouds.size(), 12u);
  const RegistrationResult r = register_views(clouds, m);
  print_prior("four views off the table", r);
  EXPECT_TRUE(r.failed_views.empty());
  EXPECT_LT(r.max_rotation_error_deg, 0.5);
  EXPECT_LT(r.max_object_translation_error, 0.001);
}


// Hand-held views of the bundled mustard bottle (no angle) after 8 table views
// at 20 degrees elevation: each shot is taken from `elevation` at `distance`,
// aimed at `target_height` (or the bottle's middle), and held turned in the hand
// (rolled about the optical axis: any rotation about the camera centre keeps the
// sensor at the origin). Each view's overlap with the table views is measured
// from the truth: the share of its points within 2 mm of a table view's point.
struct HandShot {
  double elevation, angle, distance, target_height, roll_deg;
};
struct HandHeldSession {
  std::vector<Cloud> clouds;
  SessionManifest manifest;
  std::vector<double> overlap;  // per view; 1 for the table views
};
// A lamp on the scanner, off its axis: each point's colour scaled by
// ambient + (1 - ambient) max(0, n . l) for the direction l to the lamp (camera frame)
// and the surface's normal n there: the PCA normal of the view's 24 nearest points
// (facing the camera), not the view's own per-pixel normals, which the depth noise
// tilts by some 20 degrees and which the registration's colour check itself reads (a
// lamp lights the surface, not the scanner's estimate of it). A surface point seen
// from two views is lit differently in each, as under a real scanner's light (the
// simulator's colours are the texture's, unlit).
void light_by_lamp(Cloud& c, const Vec3f& to_lamp, double ambient) {
  const Vec3f l = to_lamp.normalized();
  const std::vector<Vec3f> normals = estimate_normals(c.points, 24);
  for (std::size_t i = 0; i < c.size() && i < c.colours.size(); ++i) {
    Vec3f n = normals[i];
    if (n.dot(c.points[i]) > 0) n = -n;  // facing the camera at the origin
    const float k = float(ambient + (1 - ambient) * std::max(0.0f, n.dot(l)));
    Rgb& col = c.colours[i];
    col = Rgb{std::uint8_t(std::lround(col.r * k)), std::uint8_t(std::lround(col.g * k)),
              std::uint8_t(std::lround(col.b * k))};
  }
}

struct Lamp {
  Vec3f to_lamp;   // camera frame
  double ambient;  // the share of the texture's brightness a point facing away keeps
};
HandHeldSession hand_held_session(const std::filesystem::path& dir, const std::vector<HandShot>& hand,
                                  const Lamp* lamp = nullptr) {
  const std::string mesh = (test::source_dir() / "data" / "mustard_bottle" / "textured.obj").string();
  HandHeldSession out;
  std::vector<Cloud>& clouds = out.clouds;
  SessionManifest& m = out.manifest;
  const auto scan = [&](const std::string& name, const HandShot& s, int views, bool table) {
    std::string uri = "sim:synthetic?mesh=" + mesh + "&noise=0.0005&seed=7" +
                      (table ? "&width=320&height=240" : "&width=640&height=480&table_radius=0") +
                      "&elevation_deg=" + std::to_string(s.elevation) + "&distance=" + std::to_string(s.distance);
    if (s.target_height >= 0) uri += "&target_height=" + std::to_string(s.target_height);
    // Held in the hand: no working volume (crop off), the bottom too.
    Session session = capture_sim(dir / name, uri, views, s.angle, table);
    if (table) {
      m = session.manifest();
      for (std::size_t i = 0; i < m.views.size(); ++i) {
        clouds.push_back(session.load_view(i));
        if (lamp) light_by_lamp(clouds.back(), lamp->to_lamp, lamp->ambient);
      }
      return;
    }
    ViewRecord v = session.manifest().views.at(0);
    v.angle_deg.reset();
    Cloud c = session.load_view(0);
    const Eigen::Matrix3f R = Eigen::AngleAxisf(float(s.roll_deg * M_PI / 180), Vec3f::UnitZ()).toRotationMatrix();
    for (Vec3f& p : c.points) p = R * p;
    for (Vec3f& q : c.normals) q = R * q;
    if (lamp) light_by_lamp(c, lamp->to_lamp, lamp->ambient);  // on the scanner, turned with it
    Eigen::Matrix4d Rinv = Eigen::Matrix4d::Identity();
    Rinv.block<3, 3>(0, 0) = R.transpose().cast<double>();
    *v.reference_pose = *v.reference_pose * Rinv;
    m.views.push_back(v);
    clouds.push_back(std::move(c));
  };
  scan("table", {20, 0, 0.45, -1, 0}, 8, true);
  for (std::size_t k = 0; k < hand.size(); ++k) scan("hand" + std::to_string(k), hand[k], 1, false);
  for (std::size_t i = 0; i < 8; ++i) std::printf("  table view %zu: %zu points\n", i, clouds[i].size());
  std::vector<Vec3f> table_points;
  for (std::size_t i = 0; i < 8; ++i) {
    const Eigen::Matrix4f X = m.views[i].reference_pose->cast<float>();
    for (const Vec3f& p : clouds[i].points) table_points.push_back(X.block<3, 3>(0, 0) * p + X.block<3, 1>(0, 3));
  }
  const PointIndex table_index(std::move(table_points));
  out.overlap.assign(clouds.size(), 1.0);
  for (std::size_t i = 8; i < clouds.size(); ++i) {
    const Eigen::Matrix4f X = m.views[i].reference_pose->cast<float>();
    std::size_t n = 0, near = 0;
    for (std::size_t k = 0; k < clouds[i].size(); k += 7, ++n)
      near += table_index.nearest_within(X.block<3, 3>(0, 0) * clouds[i].points[k] + X.block<3, 1>(0, 3), 0.002f).first >= 0;
    out.overlap[i] = double(near) / double(std::max<std::size_t>(1, n));
  }
  return out;
}

// Each hand-held view (after the 8 table views) registered within 0.5 deg / 1 mm at
// the object of the truth, or failed with a message that names it; returns how many
// registered.
int hand_held_right_or_named(const HandHeldSession& s, const RegistrationResult& r) {
  int registered = 0;
  for (std::size_t i = 8; i < s.clouds.size(); ++i) {
    std::printf("  view %zu: %zu points, overlap %.2f: %s\n", i, s.clouds[i].size(), s.overlap[i],
                r.views[i].registered ? "registered" : r.views[i].message.c_str());
    if (r.views[i].registered) {
      ++registered;
      EXPECT_TRUE(r.views[i].rotation_error_deg.has_value()) << i;
      if (!r.views[i].rotation_error_deg) continue;
      EXPECT_LT(*r.views[i].rotation_error_deg, 0.5) << i;
      EXPECT_LT(*r.views[i].object_translation_error, 0.001) << i;
    } else {
      EXPECT_EQ(r.views[i].message.rfind("views[" + std::to_string(i) + "]", 0), 0u) << i << ": " << r.views[i].message;
    }
  }
  return registered;
}

// The hand-held shots of HandHeldViewsWithAThirdOverlapRegister (and, lit, of the
// lamp tests); the first nine also open
// ViewsFromNearlyStraightBelowLandRightOrFailByName.
std::vector<HandShot> hand_held_shots() {
  return {
      {70, 30, 0.45, -1, 70},       // from above: the cap and shoulders
      {-60, 100, 0.45, -1, 160},    // from below: the bottom and a band of the side
      {-50, 320, 0.30, 0.05, 45},   // nearer, below the label
      {-40, 200, 0.30, 0.05, -120}, // nearer, low down
      {-20, 250, 0.30, -1, 90},     // a little below
      // Nearly straight below: the flat bottom (which no table view saw) and a
      // band of the side; the overlap 0.27-0.52.
      {-65, 40, 0.35, -1, 30},
      {-70, 280, 0.35, -1, -60},
      {-80, 0, 0.35, -1, 100},
      {-55, 180, 0.40, -1, 10},
      {-75, 120, 0.30, 0.08, 0},    // nearer, aimed 8 cm up: overlap 0.37
  };
}

// Issue 26, item 3, as the issue states it: hand-held views (no angle) from
// above and below, nearer than the table's scanner, so that some see only a
// part of the bottle; every view with 30 % or more overlap must register within
// 0.5 deg / 1 mm at the object. With one RANSAC run at one FPFH radius
// (global_extra_seeds 0, no global_extra_radii) the two views from below
// (overlap 0.59 and 0.68) came out half-turned (179.5 and 177.7 deg, 61 and
// 55 mm at the object); the second radius and seed find them. The view from 75
// degrees below aimed 8 cm up (overlap 0.37) failed by name until the turns
// about the view's own axes and the slide along the weakest direction
// (2026-12-05): no RANSAC hypothesis came within 25 degrees of it, and the turn
// that did came to rest 23 mm off along the band it shares with the model.
TEST(SimRegistration, HandHeldViewsWithAThirdOverlapRegister) {
  test::TempDir dir("station-handheld");
  const std::vector<HandShot> hand = hand_held_shots();
  const HandHeldSession s = hand_held_session(dir.path(), hand);
  const std::vector<Cloud>& clouds = s.clouds;
  const SessionManifest& m = s.manifest;
  ASSERT_EQ(clouds.size(), 8u + hand.size());
  const RegistrationResult r = register_views(clouds, m);
  print_prior("hand-held views", r);
  // Registered or not, never wrong: a view under 30 % may fail, by name.
  hand_held_right_or_named(s, r);
  int partial = 0, assessed = 0;
  for (std::size_t i = 8; i < clouds.size(); ++i) {
    if (s.overlap[i] < 0.3) continue;
    ++assessed;
    partial += s.overlap[i] < 0.7;
    EXPECT_TRUE(r.views[i].registered) << i << ": " << r.views[i].message;
  }
  EXPECT_GE(partial, 2);  // the case holds views that see only a part of what the table saw
  EXPECT_GE(assessed, 9);  // five views from above and the side, four of the five from below
  for (std::size_t i = 0; i < 8; ++i) EXPECT_TRUE(r.views[i].registered) << i;
}

// The hand-held session above with five more views from 70-80 degrees below,
// near (0.30 m): a third of each is the band of the side the table views saw,
// the rest the flat bottom. The shape fits several of them turned or slid.
// Before the colour refusal, the slide and the free-space check (2026-12-05)
// the one at turntable angle 60 and the 0.27 view landed 99 deg / 59-60 mm
// off, silently; with the colour refusal alone, the one at turntable angle 60
// still landed 97 deg off (its colours 11.7 apart per channel, under the
// threshold; 41 % of it where the table views saw through). Each view must
// register right or fail by name.
TEST(SimRegistration, ViewsFromNearlyStraightBelowLandRightOrFailByName) {
  test::TempDir dir("station-below");
  std::vector<HandShot> hand = hand_held_shots();
  hand.resize(9);
  hand.insert(hand.end(), {
      {-75, 0, 0.30, 0.08, 30},
      {-75, 60, 0.30, 0.08, -90},
      {-70, 150, 0.30, 0.08, 120},
      {-80, 250, 0.30, 0.06, -30},
      {-75, 300, 0.30, 0.08, 0},
  });
  const HandHeldSession s = hand_held_session(dir.path(), hand);
  ASSERT_EQ(s.clouds.size(), 8u + hand.size());
  const RegistrationResult r = register_views(s.clouds, s.manifest);
  print_prior("views from nearly straight below", r);
  const int registered = hand_held_right_or_named(s, r);
  EXPECT_GE(registered, 8 + 2);  // the hand-held session's but the 0.27 view; two from below
  for (std::size_t i = 0; i < 8; ++i) EXPECT_TRUE(r.views[i].registered) << i;
}

// Issue 26: the colour checks (the refusal at 15 per channel or 2.5 x the model views'
// own median difference, the swap, the near-tie choice) under a lamp on the scanner
// instead of the simulator's unlit texture: every surface point's colour changes
// from view to view with its angle to the lamp. The hand-held session of
// HandHeldViewsWithAThirdOverlapRegister, lit; no view may land wrong. Returns how
// many hand-held views registered.
int lamp_session(const std::filesystem::path& dir, const Lamp& lamp) {
  const std::vector<HandShot> hand = hand_held_shots();
  const HandHeldSession s = hand_held_session(dir, hand, &lamp);
  if (s.clouds.size() != 8u + hand.size()) {
    ADD_FAILURE() << s.clouds.size() << " views";
    return 0;
  }
  const RegistrationResult r = register_views(s.clouds, s.manifest);
  print_prior("hand-held views under a lamp", r);
  const int registered = hand_held_right_or_named(s, r);
  std::printf("  ambient %.2f: %d of %zu hand-held views registered\n", lamp.ambient, registered, hand.size());
  for (std::size_t i = 0; i < 8; ++i) EXPECT_TRUE(r.views[i].registered) << i;
  // Each view lit differently is no near-symmetric twin: the pairs' colours under the
  // lamp (up to 30.6 per channel, their median 14) name no view.
  for (const std::string& w : r.warnings) EXPECT_EQ(w.find("overlap where their colours differ"), std::string::npos) << w;
  return registered;
}

// A harsh lamp (a point lit edge-on keeps 0.35 of its brightness) up and to one side of
// the lens, and a milder one (0.7) to the other side. With one gain per view (before
// 2026-12-06) the harsh lamp put the views from 65 and 70 degrees below (overlap 0.38
// and 0.51) 179.2 and 179.7 deg off, silently; the shading fitted as affine in the
// view's normal (colour_error) registers them. Measured: 9 of 10 under each, as unlit.
TEST(SimRegistration, HandHeldViewsUnderALampRegisterOrFailByName) {
  test::TempDir dir("station-lamp");
  EXPECT_GE(lamp_session(dir.path() / "a", Lamp{Vec3f(0.6f, -0.5f, -1.0f), 0.35}), 8);
  EXPECT_GE(lamp_session(dir.path() / "b", Lamp{Vec3f(-0.4f, 0.6f, -1.0f), 0.7}), 8);
}

}  // namespace
}  // namespace station
