// ICP on real coloured data: three consecutive hand-held Kinect frames
// (tests/data/kinect_frames, a laptop and a box on a carpet). No poses are
// known, so the check is consistency: the motion 0 -> 2 against 0 -> 1 -> 2
// (the loop), and the objectives against each other.
#include <gtest/gtest.h>

#include <cstdio>
#include <map>

#include <Eigen/Geometry>

#include "capture/capture.h"
#include "core/error.h"
#include "registration/free_space.h"
#include "registration/icp.h"
#include "test_util.h"

namespace station {
namespace {

Cloud load_frame(int k) {
  const auto dir = test::source_dir() / "tests/data/kinect_frames";
  const std::string stem = (dir / ("frame" + std::to_string(k))).string();
  Intrinsics in;
  in.fx = in.fy = 262.5;
  in.cx = 160;
  in.cy = 120;
  return frame_to_cloud(read_rgbd_frame(stem + "_depth.png", stem + "_rgb.png", in));
}

struct Motions {
  IcpResult m01, m12, m02;  // target <- source: 0 <- 1, 1 <- 2, 0 <- 2
};

TEST(KinectFrames, ObjectivesConvergeAgreeAndCloseTheLoop) {
  std::vector<PreparedView> views;
  PrepareParams pp;
  pp.voxel_size = 0.005;
  pp.normal_neighbors = 16;
  pp.intensity = true;
  for (int k = 0; k < 3; ++k) {
    const Cloud c = load_frame(k);
    ASSERT_GT(c.size(), 60000u);
    ASSERT_TRUE(c.has_colours());
    views.push_back(prepare_view(c, pp));
    ASSERT_EQ(views.back().intensity.size(), views.back().points.size());  // the colour term is live
  }
  std::map<IcpObjective, Motions> runs;
  for (IcpObjective o : {IcpObjective::kPointToPlane, IcpObjective::kColoured, IcpObjective::kGeneralized}) {
    IcpParams ip;
    ip.objective = o;
    ip.max_distance_start = 0.1;
    ip.max_distance_end = 0.02;
    Motions& m = runs[o];
    m.m01 = icp_point_to_plane(views[1], views[0], Eigen::Matrix4d::Identity(), ip);
    m.m12 = icp_point_to_plane(views[2], views[1], Eigen::Matrix4d::Identity(), ip);
    m.m02 = icp_point_to_plane(views[2], views[0], Eigen::Matrix4d::Identity(), ip);
    for (const IcpResult* r : {&m.m01, &m.m12, &m.m02}) {
      EXPECT_TRUE(r->converged) << int(o) << ": " << r->message;
      EXPECT_GT(r->fitness, 0.95) << int(o);
    }
    // The hand-held sensor moved about 0.8 degree and 8 mm between frames.
    EXPECT_GT(rotation_angle_deg(m.m01.transform), 0.5);
    EXPECT_GT((m.m01.transform.block<3, 1>(0, 3).norm()), 0.004);
    const Eigen::Matrix4d loop = rigid_inverse(m.m02.transform) * m.m01.transform * m.m12.transform;
    const double loop_rot = rotation_angle_deg(loop), loop_trans = loop.block<3, 1>(0, 3).norm();
    std::printf("objective %d: 0<-1 %.3f deg %.2f mm, loop %.4f deg %.3f mm, rmse %.2f mm\n", int(o),
                rotation_angle_deg(m.m01.transform), 1000 * m.m01.transform.block<3, 1>(0, 3).norm(), loop_rot,
                1000 * loop_trans, 1000 * m.m01.inlier_rmse);
    // Measured: point-to-plane 0.019 deg / 0.30 mm, generalized 0.024 deg /
    // 0.43 mm, coloured 0.076 deg / 0.47 mm (Kinect noise at 1-1.7 m is
    // several mm; the voxels are 5 mm). Coloured ICP closes the loop worse
    // here (docs/registration.md; not diagnosed: the frames' colour is taken
    // as registered with the depth pixel for pixel, which it is only roughly).
    const bool coloured = o == IcpObjective::kColoured;
    EXPECT_LT(loop_rot, coloured ? 0.12 : 0.04) << int(o);
    EXPECT_LT(loop_trans, 0.001) << int(o);
  }
  // The objectives agree on each motion: generalized with point-to-plane
  // within 0.025 deg / 0.44 mm (measured), coloured within 0.23 deg / 3.4 mm.
  const Motions& p2p = runs[IcpObjective::kPointToPlane];
  for (IcpObjective o : {IcpObjective::kColoured, IcpObjective::kGeneralized}) {
    const Motions& m = runs[o];
    const bool coloured = o == IcpObjective::kColoured;
    for (const auto& [a, b] : {std::pair{&p2p.m01, &m.m01}, {&p2p.m12, &m.m12}, {&p2p.m02, &m.m02}}) {
      const Eigen::Matrix4d d = rigid_inverse(a->transform) * b->transform;
      std::printf("objective %d against point-to-plane: %.4f deg %.3f mm\n", int(o), rotation_angle_deg(d),
                  1000 * d.block<3, 1>(0, 3).norm());
      EXPECT_LT(rotation_angle_deg(d), coloured ? 0.35 : 0.06) << int(o);
      EXPECT_LT((d.block<3, 1>(0, 3).norm()), coloured ? 0.005 : 0.001) << int(o);
    }
  }
  // The photometric term did take part: coloured ICP is not point-to-plane
  // under another name on these views.
  EXPECT_FALSE(runs[IcpObjective::kColoured].m01.transform.isApprox(p2p.m01.transform, 1e-9));
}

// The free-space check of registration (registration/free_space.h) on real
// depth: each frame placed by ICP against the previous frame's sight. A
// Kinect's noise (ICP's point-to-plane RMS about 2 mm at 1-1.7 m) and its
// flying pixels at depth edges put points of a right pose in front of the other
// frame's: with the margin at 3 voxels of 1 mm, 15-20 % of them counted as seen
// through; with 3 times the RMS (registration's margin), 7-8 %. Since a point
// counts only when the whole window of the other sight lies beyond it, 0-0.2 %.
// The same frame turned 20 degrees about its own centre puts a third of it there.
TEST(KinectFrames, ARightPoseIsNotSeenThroughAndATurnedOneIs) {
  const double voxel = 0.001;
  PrepareParams pp;
  pp.voxel_size = voxel;
  pp.normal_neighbors = 16;
  std::vector<PreparedView> views;
  for (int k = 0; k < 3; ++k) views.push_back(prepare_view(load_frame(k), pp));
  IcpParams ip;
  ip.max_distance_start = 0.05;
  ip.max_distance_end = 0.01;
  for (int k = 1; k < 3; ++k) {
    FreeSpace free;
    free.add(views[std::size_t(k - 1)].points, Eigen::Matrix4d::Identity());
    const IcpResult r = icp_point_to_plane(views[std::size_t(k)], views[std::size_t(k - 1)], Eigen::Matrix4d::Identity(), ip);
    ASSERT_TRUE(r.converged) << k;
    const std::vector<Vec3f>& pts = views[std::size_t(k)].points;
    const double margin = std::max(3 * voxel, 3 * r.plane_rmse), grow = 0.1;
    const double right = free.seen_through(pts, r.transform, margin, voxel, grow);
    const double voxels_only = free.seen_through(pts, r.transform, 3 * voxel, voxel, grow);
    // Turned about the placed frame's centre (up, the camera's -y).
    Vec3d c = Vec3d::Zero();
    for (const Vec3f& p : pts) c += (r.transform * p.cast<double>().homogeneous()).head<3>();
    c /= double(pts.size());
    Eigen::Matrix4d S = Eigen::Matrix4d::Identity();
    S.block<3, 3>(0, 0) = Eigen::AngleAxisd(20 * M_PI / 180, Vec3d::UnitY()).toRotationMatrix();
    S.block<3, 1>(0, 3) = c - S.block<3, 3>(0, 0) * c;
    const double wrong = free.seen_through(pts, S * r.transform, margin, voxel, grow);
    std::printf("  frame %d: ICP RMS %.2f mm; seen through: %.3f (3 voxels only: %.3f), turned 20 deg %.3f\n", k,
                1000 * r.plane_rmse, right, voxels_only, wrong);
    // Registration refuses a pose above 0.2 (kSeenThrough): a right one stays
    // well below it, a turned one above.
    EXPECT_LT(right, 0.1) << k;
    EXPECT_GT(wrong, 0.2) << k;
  }
}


TEST(KinectFrames, ImagesThatAreNotADepthFrameAreNamed) {
  const auto dir = test::source_dir() / "tests/data/kinect_frames";
  const std::string depth = (dir / "frame0_depth.png").string(), rgb = (dir / "frame0_rgb.png").string();
  Intrinsics in;
  in.fx = in.fy = 262.5;
  auto message = [&](const std::string& d, const std::string& c) {
    try {
      read_rgbd_frame(d, c, in);
    } catch (const InvalidInput& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(message(rgb, "").find("frame0_rgb.png: the depth image is not 16-bit"), std::string::npos);
  EXPECT_NE(message(depth + ".missing", rgb).find("frame0_depth.png.missing: cannot read"), std::string::npos);
  EXPECT_NE(message(depth, rgb + ".missing").find("frame0_rgb.png.missing: cannot read"), std::string::npos);
  const Frame f = read_rgbd_frame(depth, "", in);
  EXPECT_EQ(f.intrinsics.width, 320);
  EXPECT_EQ(f.depth.size(), 320u * 240u);
  EXPECT_TRUE(f.colour.empty());
}

}  // namespace
}  // namespace station
