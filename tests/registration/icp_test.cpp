// Per-view preparation and point-to-plane ICP (capture/icp.h) on analytic clouds.
#include "registration/icp.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>

#include "core/kdtree.h"
#include "core/normals.h"

namespace station {
namespace {

// The front half (facing the sensor at the origin) of a bumpy ellipsoid 0.5 m
// ahead: no symmetry, so ICP is well posed. Random samples, seeded.
std::vector<Vec3f> bumpy_front(int n, unsigned seed, double noise) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  std::normal_distribution<double> g(0, noise);
  std::vector<Vec3f> pts;
  while (int(pts.size()) < n) {
    Vec3d d(u(rng), u(rng), u(rng));
    if (d.norm() < 1e-3 || d.norm() > 1) continue;
    d.normalize();
    if (d.z() > 0.1) continue;  // keep the half facing the sensor (-z side)
    const double r = 1 + 0.15 * std::sin(5 * d.x()) * std::cos(4 * d.y()) + 0.1 * d.x() * d.y();
    const Vec3d p = Vec3d(0.08 * d.x(), 0.05 * d.y(), 0.06 * d.z()) * r + Vec3d(0.01, 0.0, 0.5);
    pts.push_back((p + Vec3d(0, 0, g(rng))).cast<float>());
  }
  return pts;
}

PreparedView prepared(std::vector<Vec3f> pts) {
  Cloud c;
  c.points = std::move(pts);
  PrepareParams p;
  p.voxel_size = 0.001;
  return prepare_view(c, p);
}

Eigen::Matrix4d transform_of(double angle_deg, const Vec3d& axis, const Vec3d& t) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<3, 3>(0, 0) = Eigen::AngleAxisd(angle_deg * M_PI / 180, axis.normalized()).toRotationMatrix();
  T.block<3, 1>(0, 3) = t;
  return T;
}

std::vector<Vec3f> moved(const std::vector<Vec3f>& pts, const Eigen::Matrix4d& T) {
  std::vector<Vec3f> out;
  for (const Vec3f& p : pts) out.push_back((T * p.cast<double>().homogeneous()).head<3>().cast<float>());
  return out;
}

TEST(Prepare, DownsamplesRemovesOutliersAndOrientsNormals) {
  std::vector<Vec3f> pts = bumpy_front(20000, 1, 0.0);
  pts.push_back(Vec3f(0.5f, 0.5f, 0.2f));  // a lone outlier
  pts.push_back(Vec3f(std::nanf(""), 0, 0));
  Cloud c;
  c.points = pts;
  PrepareParams p;
  p.voxel_size = 0.004;
  const PreparedView v = prepare_view(c, p);
  EXPECT_EQ(v.dropped_nonfinite, 1u);
  EXPECT_GE(v.dropped_outliers, 1u);
  for (const Vec3f& q : v.full.points) EXPECT_GT(q.z(), 0.3f);
  EXPECT_LT(v.points.size(), v.full.size() / 4);
  ASSERT_EQ(v.normals.size(), v.points.size());
  for (std::size_t i = 0; i < v.points.size(); ++i) {
    EXPECT_NEAR(v.normals[i].norm(), 1.f, 1e-4f);
    EXPECT_GE(v.normals[i].dot(-v.points[i]), 0.f);  // faces the sensor
  }
  // Downsampled points are voxel centroids: within a voxel diagonal of an input point.
  const PointIndex idx(v.full.points);
  for (const Vec3f& q : v.points) EXPECT_LT(idx.nearest(q).second, 0.004f * 1.8f);
}

TEST(Icp, RecoversKnownTransformFromFiveDegreesAndTwoPercentOff) {
  const double diag = 0.2;
  // Target and source sample the surface independently and overlap partially.
  std::vector<Vec3f> target_pts, source_world;
  for (const Vec3f& p : bumpy_front(30000, 2, 0.0001)) if (p.x() < 0.05f) target_pts.push_back(p);
  for (const Vec3f& p : bumpy_front(30000, 3, 0.0001)) if (p.x() > -0.03f) source_world.push_back(p);
  const Eigen::Matrix4d truth = transform_of(20, Vec3d(0.1, 1, 0.2), Vec3d(0.01, -0.02, 0.015));
  const PreparedView target = prepared(target_pts);
  const PreparedView source = prepared(moved(source_world, rigid_inverse(truth)));
  // Start 5 degrees and 2 % of the diagonal off.
  // (5 degrees about the object's centre, not the far-away scanner origin).
  const Vec3d c(0.01, 0, 0.5);
  const Eigen::Matrix4d R5 = transform_of(5, Vec3d(1, -0.5, 0.3), Vec3d::Zero());
  Eigen::Matrix4d off = transform_of(0, Vec3d::UnitZ(), c + Vec3d(0.02 * diag, 0, 0)) * R5 *
                        transform_of(0, Vec3d::UnitZ(), -c);
  const Eigen::Matrix4d start = off * truth;
  IcpParams ip;
  ip.max_distance_start = 0.1 * diag;
  ip.max_distance_end = 0.003;
  const IcpResult r = icp_point_to_plane(source, target, start, ip);
  ASSERT_TRUE(r.converged) << r.message;
  EXPECT_LT(rotation_angle_deg(rigid_inverse(truth) * r.transform), 0.05);
  EXPECT_LT((r.transform.block<3, 1>(0, 3) - truth.block<3, 1>(0, 3)).norm(), 2e-4);
  EXPECT_GT(r.fitness, 0.5);
  EXPECT_LT(r.inlier_rmse, 0.001);
  EXPECT_GT(r.correspondences, 1000u);
  // Same input, same output (parallel reductions in a fixed order).
  const IcpResult again = icp_point_to_plane(source, target, start, ip);
  EXPECT_EQ(again.transform, r.transform);
  // The symmetric variant gets there too; point-to-point converges to a pose
  // biased by the partial overlap (border points pull), hence the wider bound.
  for (IcpObjective o : {IcpObjective::kSymmetric, IcpObjective::kPointToPoint}) {
    ip.objective = o;
    ip.max_iterations = 200;  // point-to-point converges linearly, slowly
    const IcpResult v = icp_point_to_plane(source, target, start, ip);
    ASSERT_TRUE(v.converged) << v.message;
    EXPECT_LT(rotation_angle_deg(rigid_inverse(truth) * v.transform),
              o == IcpObjective::kSymmetric ? 0.05 : 0.6) << int(o) << " it " << v.iterations;
  }
}

// The neighbour graph's promise (icp.h): every point off a point's list lies at
// least `reach` from it. Checked against all pairs, duplicates included.
TEST(NeighbourGraphTest, EveryPointOffTheListIsAtLeastReachAway) {
  std::vector<Vec3f> pts = bumpy_front(1500, 11, 0.0005);
  pts.push_back(pts[7]);  // a duplicate
  pts.push_back(pts[7]);
  const PointIndex index(pts);
  const NeighbourGraph g = neighbour_graph(index);
  constexpr int K = NeighbourGraph::kNeighbours;
  ASSERT_EQ(g.reach.size(), pts.size());
  std::size_t finite_reach = 0;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const std::uint32_t* nb = g.neighbours.data() + i * K;
    finite_reach += std::isfinite(g.reach[i]);
    for (std::size_t j = 0; j < pts.size(); ++j) {
      if (j == i || std::find(nb, nb + K, std::uint32_t(j)) != nb + K) continue;
      ASSERT_GE((pts[j] - pts[i]).norm(), g.reach[i] * (1 - 1e-6f)) << i << " " << j;
    }
  }
  EXPECT_EQ(finite_reach, pts.size());
  // K + 1 points or fewer: every other point listed, nothing beyond; K + 2: one beyond.
  for (int size : {K, K + 1, K + 2}) {
    const std::vector<Vec3f> few(pts.begin(), pts.begin() + size);
    const NeighbourGraph small = neighbour_graph(PointIndex(few));
    for (std::size_t i = 0; i < few.size(); ++i) {
      EXPECT_EQ(std::isinf(small.reach[i]), size <= K + 1) << size;
      if (size == K + 2) {
        const std::uint32_t* nb = small.neighbours.data() + i * K;
        for (std::size_t j = 0; j < few.size(); ++j)
          if (j != i && std::find(nb, nb + K, std::uint32_t(j)) == nb + K)
            EXPECT_FLOAT_EQ((few[j] - few[i]).norm(), small.reach[i]);
      }
    }
  }
  // A point with more than K + 1 copies of itself: no promise from it (reach 0 or
  // the copies' distance 0), never a wrong one.
  std::vector<Vec3f> copies(20, pts[3]);
  copies.insert(copies.end(), pts.begin() + 10, pts.begin() + 60);
  const NeighbourGraph cg = neighbour_graph(PointIndex(copies));
  for (std::size_t i = 0; i < 20; ++i) EXPECT_EQ(cg.reach[i], 0.f) << i;
}

// ICP with the neighbour graph finds the very correspondences the k-d tree does:
// the same iterations, transform and diagnostics, bit for bit, from near and far
// starts and with the coarse stride.
TEST(Icp, TheNeighbourGraphGivesTheTreesCorrespondences) {
  std::vector<Vec3f> target_pts, source_world;
  for (const Vec3f& p : bumpy_front(30000, 12, 0.0003)) if (p.x() < 0.05f) target_pts.push_back(p);
  for (const Vec3f& p : bumpy_front(30000, 13, 0.0003)) if (p.x() > -0.03f) source_world.push_back(p);
  const Eigen::Matrix4d truth = transform_of(20, Vec3d(0.1, 1, 0.2), Vec3d(0.01, -0.02, 0.015));
  const PreparedView target = prepared(target_pts);
  PreparedView bare = prepared(target_pts);
  ASSERT_FALSE(bare.graph.empty());
  bare.graph = NeighbourGraph{};
  const PreparedView source = prepared(moved(source_world, rigid_inverse(truth)));
  const Vec3d c(0.01, 0, 0.5);
  for (double deg : {1.0, 6.0}) {
    const Eigen::Matrix4d off = transform_of(0, Vec3d::UnitZ(), c + Vec3d(0.002 * deg, 0, 0)) *
                                transform_of(deg, Vec3d(1, -0.5, 0.3), Vec3d::Zero()) *
                                transform_of(0, Vec3d::UnitZ(), -c);
    for (int stride : {1, 4}) {
      IcpParams ip;
      ip.max_distance_start = 0.02;
      ip.max_distance_end = 0.002;
      ip.coarse_stride = stride;
      const IcpResult a = icp_point_to_plane(source, target, off * truth, ip);
      const IcpResult b = icp_point_to_plane(source, bare, off * truth, ip);
      ASSERT_TRUE(a.converged) << a.message;
      // The graph answered most queries (else this compares the tree with itself).
      EXPECT_GT(a.graph_answers, a.queries / 3) << deg << " " << stride;
      EXPECT_EQ(b.graph_answers, 0u);
      EXPECT_EQ(a.queries, b.queries);
      EXPECT_EQ(a.iterations, b.iterations) << deg << " " << stride;
      EXPECT_EQ(a.transform, b.transform) << deg << " " << stride;
      EXPECT_EQ(a.correspondences, b.correspondences);
      EXPECT_EQ(a.inlier_rmse, b.inlier_rmse);
      EXPECT_EQ(a.plane_rmse, b.plane_rmse);
      EXPECT_EQ(a.hessian, b.hessian);
    }
  }
  // Every target point twice (a merged model where two views' points coincide):
  // each nearest is tied, the graph gives way to the tree, and the result is the tree's.
  PreparedView twice = bare;
  twice.points.insert(twice.points.end(), bare.points.begin(), bare.points.end());
  twice.normals.insert(twice.normals.end(), bare.normals.begin(), bare.normals.end());
  twice.index = std::make_shared<PointIndex>(twice.points);
  PreparedView twice_bare = twice;
  twice.graph = neighbour_graph(*twice.index);
  IcpParams ip;
  ip.max_distance_start = 0.02;
  ip.max_distance_end = 0.002;
  const IcpResult a = icp_point_to_plane(source, twice, truth, ip);
  const IcpResult b = icp_point_to_plane(source, twice_bare, truth, ip);
  ASSERT_TRUE(a.converged) << a.message;
  EXPECT_EQ(a.graph_answers, 0u);
  EXPECT_EQ(a.transform, b.transform);
  EXPECT_EQ(a.hessian, b.hessian);
}

// The full cloud's normals from the outlier removal's search are the ones a search
// over the kept points gives, also where removed outliers crowd a point's list.
TEST(Prepare, FullNormalsFromTheOutlierSearchAreTheKeptPointsOwn) {
  std::vector<Vec3f> pts = bumpy_front(8000, 14, 0.0002);
  std::mt19937 rng(15);
  std::normal_distribution<float> g(0, 0.004f);
  // Strays a few millimetres off the surface: removed, and in kept points' rows.
  for (int k = 0; k < 200; ++k) pts.push_back(pts[std::size_t(k) * 37] + Vec3f(g(rng), g(rng), g(rng)) * 0.75f);
  Cloud c;
  c.points = pts;
  PrepareParams p;
  p.voxel_size = 0.001;
  // Rows of 10 (the point and 9 neighbours) for 10 normal neighbours: a point with
  // one removed neighbour in its row is searched again, the others are not.
  p.outlier_neighbors = 9;
  p.full_normal_neighbors = 10;
  const PreparedView v = prepare_view(c, p);
  ASSERT_GT(v.dropped_outliers, 0u);
  ASSERT_EQ(v.full_normals.size(), v.full.size());
  const std::vector<Vec3f> direct = estimate_normals(PointIndex(v.full.points), 10);
  std::size_t same = 0;
  for (std::size_t i = 0; i < direct.size(); ++i) {
    EXPECT_GT(std::abs(direct[i].dot(v.full_normals[i])), 0.9999f) << i;
    same += direct[i] == v.full_normals[i];
  }
  // (Bit for bit but where equal distances order two neighbours differently.)
  EXPECT_GE(same, direct.size() - 2);
  p.full_normal_neighbors = 0;
  EXPECT_TRUE(prepare_view(c, p).full_normals.empty());
}

TEST(Icp, ReportsFailureOnNonOverlappingAndEmptyViews) {
  const PreparedView target = prepared(bumpy_front(5000, 4, 0));
  // The same shape a metre away: nothing within the correspondence distance.
  const PreparedView far = prepared(moved(bumpy_front(5000, 5, 0), transform_of(0, Vec3d::UnitZ(), Vec3d(1, 0, 0))));
  IcpResult r = icp_point_to_plane(far, target, Eigen::Matrix4d::Identity());
  EXPECT_FALSE(r.converged);
  EXPECT_NE(r.message.find("correspondences"), std::string::npos) << r.message;

  // Barely touching: a few matches, far below the overlap guard.
  std::vector<Vec3f> sliver;
  for (const Vec3f& p : bumpy_front(5000, 6, 0)) if (p.x() > 0.075f) sliver.push_back(p);
  std::vector<Vec3f> rest;
  for (const Vec3f& p : bumpy_front(20000, 7, 0)) if (p.x() > 0.07f || p.x() < -0.05f) rest.push_back(p);
  IcpParams ip;
  ip.min_fitness = 0.5;
  r = icp_point_to_plane(prepared(rest), prepared(sliver), Eigen::Matrix4d::Identity(), ip);
  EXPECT_FALSE(r.converged);
  EXPECT_FALSE(r.message.empty());

  const PreparedView empty = prepared({});
  r = icp_point_to_plane(empty, target, Eigen::Matrix4d::Identity());
  EXPECT_FALSE(r.converged);
  EXPECT_NE(r.message.find("no points"), std::string::npos);
  std::vector<Vec3f> nans(100, Vec3f(std::nanf(""), 0, 1));
  const PreparedView nan_view = prepared(nans);
  EXPECT_TRUE(nan_view.points.empty());
  EXPECT_EQ(nan_view.dropped_nonfinite, 100u);
  EXPECT_FALSE(icp_point_to_plane(target, nan_view, Eigen::Matrix4d::Identity()).converged);
  Eigen::Matrix4d bad = Eigen::Matrix4d::Identity();
  bad(0, 3) = std::nan("");
  EXPECT_FALSE(icp_point_to_plane(target, target, bad).converged);
}

}  // namespace
}  // namespace station
