#include "registration/icp.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cstdint>
#include <cmath>
#include <limits>
#include <tuple>
#include <unordered_map>

#include "registration/coloured_icp.h"
#include "registration/viewpoint.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/sampling.h"

namespace station {

namespace {

constexpr double kDeg = M_PI / 180.0;

// Accumulated normal equations; reduced over threads in a fixed split order.
struct Normal6 {
  Matrix6d A = Matrix6d::Zero();
  Vector6d b = Vector6d::Zero();
  double sq_euclid = 0, sq_plane = 0;
  std::size_t n = 0;
  std::size_t queries = 0, graph_answers = 0;  // nearest-point queries, and those the graph answered
  void add(const Normal6& o) {
    A += o.A;
    b += o.b;
    sq_euclid += o.sq_euclid;
    sq_plane += o.sq_plane;
    n += o.n;
    queries += o.queries;
    graph_answers += o.graph_answers;
  }
};

}  // namespace

Eigen::Matrix4d motion_exp(const Vector6d& x) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  const Vec3d w = x.head<3>();
  const double angle = w.norm();
  if (angle > 0) T.block<3, 3>(0, 0) = Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
  T.block<3, 1>(0, 3) = x.tail<3>();
  return T;
}

Eigen::Matrix4d rigid_inverse(const Eigen::Matrix4d& T) {
  Eigen::Matrix4d inv = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d Rt = T.block<3, 3>(0, 0).transpose();
  inv.block<3, 3>(0, 0) = Rt;
  inv.block<3, 1>(0, 3) = -Rt * T.block<3, 1>(0, 3);
  return inv;
}

double rotation_angle_deg(const Eigen::Matrix4d& T) {
  const double c = std::clamp((T.block<3, 3>(0, 0).trace() - 1.0) / 2.0, -1.0, 1.0);
  // acos loses precision near 0; use the sine part too.
  const Eigen::Matrix3d R = T.block<3, 3>(0, 0);
  const double s = 0.5 * Vec3d(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1)).norm();
  return std::atan2(s, c) / kDeg;
}

namespace {

std::vector<Vec3f> unoriented_normals(const PointIndex& index, int k) {
  return k >= 3 ? estimate_normals(index, k) : std::vector<Vec3f>(index.points().size(), Vec3f::Zero());
}

// The PCA normals of the kept points `kept_points` (finite's `keep`), unoriented,
// as estimate_normals(PointIndex(kept_points), k) gives them: each point's k nearest
// kept points are the first k kept ones of its nearest among all the finite points
// (`near`: statistical_inliers' rows, closest first), where that row holds k of
// them; the other points (and every point without rows) are searched again.
std::vector<Vec3f> kept_normals(std::size_t finite_count, const std::vector<std::size_t>& keep,
                                const std::vector<std::uint32_t>& near, const std::vector<Vec3f>& kept_points,
                                const PrepareParams& params) {
  const int k = params.full_normal_neighbors;
  const std::size_t row = std::size_t(params.outlier_neighbors) + 1;
  if (near.size() != finite_count * row || kept_points.size() <= std::size_t(k))
    return kept_points.empty() ? std::vector<Vec3f>() : estimate_normals(PointIndex(kept_points), k);
  std::vector<std::int32_t> at(finite_count, -1);  // finite index -> kept index
  for (std::size_t m = 0; m < keep.size(); ++m) at[keep[m]] = std::int32_t(m);
  std::vector<Vec3f> normals(kept_points.size(), Vec3f::Zero());
  std::vector<char> searched(kept_points.size(), 0);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, keep.size(), 256), [&](const tbb::blocked_range<std::size_t>& r) {
    std::vector<Vec3d> nb(static_cast<std::size_t>(k));
    for (std::size_t m = r.begin(); m != r.end(); ++m) {
      const std::uint32_t* row_of = near.data() + keep[m] * row;
      int found = 0;
      for (std::size_t t = 0; t < row && found < k; ++t) {
        if (row_of[t] == std::numeric_limits<std::uint32_t>::max()) break;
        const std::int32_t j = at[row_of[t]];
        if (j >= 0) nb[std::size_t(found++)] = kept_points[std::size_t(j)].cast<double>();
      }
      if (found < k) searched[m] = 1;
      else normals[m] = pca_normal(nb.data(), found).cast<float>();
    }
  });
  if (std::find(searched.begin(), searched.end(), 1) == searched.end()) return normals;
  const PointIndex index(kept_points);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, keep.size(), 256), [&](const tbb::blocked_range<std::size_t>& r) {
    std::vector<std::uint32_t> idx(static_cast<std::size_t>(k));
    std::vector<float> dsq(idx.size());
    std::vector<Vec3d> nb(idx.size());
    for (std::size_t m = r.begin(); m != r.end(); ++m) {
      if (!searched[m]) continue;
      const int found = index.knn_into(kept_points[m], k, idx.data(), dsq.data());
      for (int t = 0; t < found; ++t) nb[std::size_t(t)] = kept_points[idx[std::size_t(t)]].cast<double>();
      normals[m] = pca_normal(nb.data(), found).cast<float>();
    }
  });
  return normals;
}

}  // namespace

NeighbourGraph neighbour_graph(const PointIndex& index) {
  constexpr int K = NeighbourGraph::kNeighbours;
  const std::vector<Vec3f>& points = index.points();
  NeighbourGraph g;
  g.neighbours.assign(points.size() * K, std::numeric_limits<std::uint32_t>::max());
  g.reach.assign(points.size(), std::numeric_limits<float>::infinity());
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 512), [&](const tbb::blocked_range<std::size_t>& r) {
    std::uint32_t idx[K + 2];
    float dsq[K + 2];
    for (std::size_t i = r.begin(); i != r.end(); ++i) {
      const int found = index.knn_into(points[i], K + 2, idx, dsq);
      int others = 0;
      for (int t = 0; t < found; ++t) {
        if (idx[t] == i) continue;  // (first, or after a duplicate of it)
        if (others < K) g.neighbours[i * K + std::size_t(others)] = idx[t];
        else if (others == K) g.reach[i] = std::sqrt(dsq[t]);
        ++others;
      }
      // K + 2 found without the point itself among them: the last one may not be the
      // (K+1)-th other point's nearest rival; no proof from this point then.
      if (found == K + 2 && others > K + 1) g.reach[i] = 0;
    }
  });
  return g;
}

std::vector<Vec3f> pca_normals(const PointIndex& index, int k, const Vec3f& viewpoint) {
  std::vector<Vec3f> normals = unoriented_normals(index, k);
  orient_normals_towards(index.points(), normals, viewpoint, true);
  return normals;
}

PreparedView prepare_view(const Cloud& cloud, const PrepareParams& params) {
  PreparedView v;
  // Non-finite points first: a NaN would poison the index and every sum.
  Cloud finite;
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    if (!cloud.points[i].allFinite()) continue;
    finite.points.push_back(cloud.points[i]);
    if (cloud.has_normals() && cloud.normals.size() == cloud.size())
      finite.normals.push_back(cloud.normals[i]);
    if (cloud.has_colours() && cloud.colours.size() == cloud.size())
      finite.colours.push_back(cloud.colours[i]);
  }
  if (finite.normals.size() != finite.size()) finite.normals.clear();
  if (finite.colours.size() != finite.size()) finite.colours.clear();
  v.dropped_nonfinite = cloud.size() - finite.size();

  const bool full_normals = params.full_normal_neighbors >= 3 && !finite.has_normals();
  std::vector<std::uint32_t> near;  // the outlier search's neighbours, reused for the normals
  const std::vector<std::size_t> keep = statistical_inliers(
      finite.points, params.outlier_neighbors, params.outlier_std_ratio,
      full_normals && params.outlier_neighbors + 1 >= params.full_normal_neighbors ? &near : nullptr);
  v.dropped_outliers = finite.size() - keep.size();
  for (std::size_t i : keep) {
    v.full.points.push_back(finite.points[i]);
    if (finite.has_normals()) v.full.normals.push_back(finite.normals[i]);
    if (finite.has_colours()) v.full.colours.push_back(finite.colours[i]);
  }
  if (full_normals) v.full_normals = kept_normals(finite.size(), keep, near, v.full.points, params);
  v.points = voxel_downsample(v.full.points, params.voxel_size);
  v.index = std::make_shared<PointIndex>(v.points);
  v.graph = neighbour_graph(*v.index);
  v.normals = unoriented_normals(*v.index, params.normal_neighbors);
  const ViewpointEstimate sensor = estimate_viewpoint(v.points, v.normals);
  v.viewpoint = sensor.viewpoint;
  v.viewpoint_at_origin = sensor.at_origin;
  v.grazing_origin = sensor.grazing_origin;
  orient_normals_towards(v.points, v.normals, v.viewpoint, true);
  if (params.intensity && v.full.has_colours() && !v.points.empty()) {
    const PointIndex full_index(v.full.points);
    v.intensity = sample_intensity(v.points, full_index, intensities(v.full.colours), 0.5 * params.voxel_size);
    v.intensity_gradient = intensity_gradients(*v.index, v.normals, v.intensity, params.normal_neighbors);
  }
  return v;
}

IcpResult icp_point_to_plane(const PreparedView& source, const PreparedView& target,
                             const Eigen::Matrix4d& initial, const IcpParams& params) {
  IcpResult res;
  res.transform = initial;
  if (source.points.empty() || target.points.empty() || !target.index) {
    res.message = source.points.empty() ? "source view has no points" : "target view has no points";
    return res;
  }
  if (!initial.allFinite()) {
    res.message = "initial transform is not finite";
    return res;
  }
  const std::vector<Vec3f>& tp = target.points;
  const std::vector<Vec3f>& tn = target.normals;
  const double cos_max = std::cos(params.max_normal_angle_deg * kDeg);
  const bool symmetric = params.objective == IcpObjective::kSymmetric;
  const bool point_to_point = params.objective == IcpObjective::kPointToPoint;
  const bool coloured = params.objective == IcpObjective::kColoured &&
                       source.intensity.size() == source.points.size() &&
                       target.intensity.size() == tp.size() && target.intensity_gradient.size() == tp.size();
  const double lambda = std::clamp(params.coloured_lambda, 0.0, 1.0);
  // The colour term's weight, scaled to the final distance: its Jacobian grows as
  // 1 / length (an intensity gradient) where the geometric one does not, so the
  // paper's lambda, set for scenes matched at centimetres, would let colour noise
  // outweigh the geometry by (d_ref / d_end)^2 on an object matched at a millimetre.
  // The paper's lambda balances residuals in metres: r_G^2 grows by units_per_metre^2
  // in other units and r_C not, so the colour term's weight grows with it.
  const double ref = params.coloured_reference_distance;
  const double colour_weight =
      (1 - lambda) * params.units_per_metre * params.units_per_metre *
      (ref > 0 ? std::pow(std::max(params.max_distance_end, 1e-9 * params.units_per_metre) / ref, 2) : 1.0);
  const bool generalized = params.objective == IcpObjective::kGeneralized;
  const double eps = std::clamp(params.gicp_epsilon, 1e-6, 1.0);
  const double shrink = std::clamp(params.shrink, 0.05, 1.0);
  const double d_end = params.max_distance_end;
  double d_max = std::max(params.max_distance_start, d_end);
  Eigen::Matrix4d T = initial;
  // Each source point's last correspondence: at the next pose its distance bounds
  // the nearest-neighbour search (the nearest point is at most that far), which
  // prunes most of the k-d tree; the correspondences are the same.
  std::vector<std::int32_t> last(source.points.size(), -1);
  const bool walk = target.graph.reach.size() == tp.size();
  // |x - q|^2 as the index computes it (nanoflann's squared sum in float, x then y
  // then z), so a nearest found by the graph has the same distance, bit for bit.
  const auto dist_sq = [&](const Vec3f& x, std::uint32_t j) {
    const Vec3f& q = tp[j];
    const float dx = x.x() - q.x(), dy = x.y() - q.y(), dz = x.z() - q.z();
    float d2 = dx * dx;
    d2 += dy * dy;
    d2 += dz * dz;
    return d2;
  };
  constexpr int kWalkSteps = 4;

  // One pass of correspondences + normal equations at the current T and d_max.
  const auto linearise = [&](const Eigen::Matrix4d& Tc, double dmax, std::size_t stride) {
    const Eigen::Matrix3f R = Tc.block<3, 3>(0, 0).cast<float>();
    const Vec3f t = Tc.block<3, 1>(0, 3).cast<float>();
    const double huber = params.huber_fraction > 0 ? params.huber_fraction * dmax : 0.0;
    const std::size_t grain = 256;
    const std::size_t count = (source.points.size() + stride - 1) / stride;
    // Deterministic reduction: the same split and join order on every run.
    return tbb::parallel_deterministic_reduce(
        tbb::blocked_range<std::size_t>(0, count, grain), Normal6{},
        [&](const tbb::blocked_range<std::size_t>& r, Normal6 acc) {
          for (std::size_t k = r.begin(); k != r.end(); ++k) {
            const std::size_t i = k * stride;
            const Vec3f p = R * source.points[i] + t;
            int j = -1;
            float dist = 0;
            float bound = float(dmax);
            // (A relative margin over float rounding keeps the last point itself inside.)
            if (last[i] >= 0) bound = std::min(bound, (p - tp[std::size_t(last[i])]).norm() * (1 + 1e-5f));
            bool settled = false;  // the nearest point is known, and whether it lies within bound
            if (walk && last[i] >= 0) {
              // From the last correspondence down the neighbour graph to a point nearer
              // than all its neighbours, taken where the graph proves it the nearest of all
              // (NeighbourGraph); else the search below.
              std::uint32_t c = std::uint32_t(last[i]);
              float dc = dist_sq(p, c);
              for (int step = 0; step < kWalkSteps; ++step) {
                std::uint32_t best = c;
                float db = dc;
                bool tied = false;  // a neighbour exactly as near as c: which one the tree returns is its own affair
                const std::uint32_t* nb = target.graph.neighbours.data() + std::size_t(c) * NeighbourGraph::kNeighbours;
                for (int t = 0; t < NeighbourGraph::kNeighbours && nb[t] != std::numeric_limits<std::uint32_t>::max(); ++t) {
                  const float dn = dist_sq(p, nb[t]);
                  tied = tied || dn == dc;
                  if (dn < db) {
                    best = nb[t];
                    db = dn;
                  }
                }
                if (best != c) {
                  c = best;
                  dc = db;
                  continue;
                }
                if (!tied && 2 * std::sqrt(dc) < target.graph.reach[c] * (1 - 1e-4f)) {
                  settled = true;
                  // Within the bound as the search bounds it (its squared bound, the next
                  // float up), or nothing found, as the search would: last unchanged.
                  if (dc < std::nextafter(bound * bound, std::numeric_limits<float>::infinity())) {
                    j = int(c);
                    dist = std::sqrt(dc);
                    last[i] = j;
                  }
                }
                break;
              }
            }
            ++acc.queries;
            if (settled) ++acc.graph_answers;
            else {
              std::tie(j, dist) = target.index->nearest_within(p, bound);
              if (j >= 0) last[i] = j;
            }
            if (j < 0 || dist > dmax) continue;
            const Vec3f& n = tn[j];
            Vec3f ns = Vec3f::Zero();
            if (!source.normals.empty()) {
              ns = R * source.normals[i];
              if (double(ns.dot(n)) < cos_max) continue;
            }
            const Vec3d pd = p.cast<double>();
            // Symmetric objective: the mean of both normals cancels the
            // first-order bias of either normal (Rusinkiewicz 2019).
            const Vec3d nd = (symmetric && !source.normals.empty()) ? Vec3d((n + ns).normalized().cast<double>())
                                                                   : Vec3d(n.cast<double>());
            const double res_plane = nd.dot(pd - tp[j].cast<double>());
            if (generalized) {
              // Plane-to-plane: r^T (C_q + R C_p R^T)^-1 r, scaled by 2 eps so
              // that two aligned planes weigh the normal direction by 1 (the
              // Hessian is then comparable with point-to-plane's).
              const Vec3d r3 = pd - tp[j].cast<double>();
              const Vec3d nq = n.cast<double>();
              Eigen::Matrix3d C = Eigen::Matrix3d::Identity() - (1 - eps) * nq * nq.transpose();
              if (!source.normals.empty()) {
                const Vec3d np = ns.cast<double>();
                C += Eigen::Matrix3d::Identity() - (1 - eps) * np * np.transpose();
              } else {
                C += eps * Eigen::Matrix3d::Identity();
              }
              const Eigen::Matrix3d M = 2 * eps * C.inverse();
              Eigen::Matrix<double, 3, 6> J3;
              J3.block<3, 3>(0, 0) << 0, pd.z(), -pd.y(), -pd.z(), 0, pd.x(), pd.y(), -pd.x(), 0;
              J3.block<3, 3>(0, 3).setIdentity();
              const double a = std::sqrt(std::max(0.0, r3.dot(M * r3)));
              const double w = (huber > 0 && a > huber) ? huber / a : 1.0;
              acc.A.noalias() += w * J3.transpose() * M * J3;
              acc.b.noalias() += w * J3.transpose() * (M * r3);
            } else if (point_to_point) {
              // Three residuals p - q with d/dx = [-[p]x, I].
              const Vec3d r3 = pd - tp[j].cast<double>();
              Eigen::Matrix<double, 3, 6> J3;
              J3.block<3, 3>(0, 0) << 0, pd.z(), -pd.y(), -pd.z(), 0, pd.x(), pd.y(), -pd.x(), 0;
              J3.block<3, 3>(0, 3).setIdentity();
              const double a = r3.norm();
              const double w = (huber > 0 && a > huber) ? huber / a : 1.0;
              acc.A.noalias() += w * J3.transpose() * J3;
              acc.b.noalias() += w * J3.transpose() * r3;
            } else {
              Vector6d J;
              J.head<3>() = pd.cross(nd);
              J.tail<3>() = nd;
              // Huber weight: quadratic near zero, linear beyond the threshold.
              const double a = std::abs(res_plane);
              const double w = (huber > 0 && a > huber) ? huber / a : 1.0;
              const double wg = coloured ? lambda : 1.0;
              acc.A.noalias() += wg * w * J * J.transpose();
              acc.b.noalias() += wg * w * J * res_plane;
              if (coloured) {
                // Photometric term: the target's intensity continued along its
                // tangent plane to p's projection, against the source intensity.
                const Vec3d q = tp[j].cast<double>();
                const Vec3d d = target.intensity_gradient[j].cast<double>();
                const Vec3d g = d - nd * nd.dot(d);
                const Vec3d pp = pd - nd * res_plane;
                const double rc = double(target.intensity[j]) + d.dot(pp - q) - double(source.intensity[i]);
                Vector6d Jc;
                Jc.head<3>() = pd.cross(g);
                Jc.tail<3>() = g;
                acc.A.noalias() += colour_weight * Jc * Jc.transpose();
                acc.b.noalias() += colour_weight * Jc * rc;
              }
            }
            acc.sq_euclid += double(dist) * double(dist);
            acc.sq_plane += res_plane * res_plane;
            ++acc.n;
          }
          return acc;
        },
        [](Normal6 a, const Normal6& b) {
          a.add(b);
          return a;
        },
        tbb::simple_partitioner());
  };

  bool small_step = false;
  Vector6d prev_step = Vector6d::Zero();
  double damping = 1.0;
  int end_iterations = 0;  // iterations run at the final distance
  constexpr int kUndampedEndIterations = 15;
  // Before the final distance, every coarse_stride-th source point (the pull
  // of a coarse stage needs no more); at the final distance all of them.
  const std::size_t coarse_stride = std::size_t(std::max(1, params.coarse_stride));
  for (int it = 0; it < params.max_iterations; ++it) {
    const bool at_end = d_max <= d_end * (1 + 1e-9);  // d_max changes only at the bottom
    const Normal6 sys = linearise(T, d_max, at_end ? 1 : coarse_stride);
    res.iterations = it + 1;
    res.queries += sys.queries;
    res.graph_answers += sys.graph_answers;
    if (sys.n < std::size_t(std::max(params.min_correspondences, 6))) {
      res.message = "too few correspondences (" + std::to_string(sys.n) + " within " +
                    std::to_string(1000 * d_max / params.units_per_metre) + " mm)";
      res.correspondences = sys.n;
      return res;
    }
    // A tiny ridge keeps a rank-deficient (degenerate) system solvable; the
    // caller detects degeneracy from the Hessian itself.
    const double ridge = 1e-9 * sys.A.trace() / 6.0;
    Vector6d x = (sys.A + ridge * Matrix6d::Identity()).ldlt().solve(-sys.b);
    if (!x.allFinite()) {
      res.message = "ill-posed point-to-plane system";
      return res;
    }
    if (at_end) ++end_iterations;
    if (coloured || end_iterations > kUndampedEndIterations) {
      // The photometric term can make the nearest neighbours flip back and
      // forth (a period-2 cycle on regular samplings): a step that reverses
      // the previous one halves the step length from then on. Geometric
      // objectives can cycle the same way at the final distance (a sparse,
      // noisy overlap whose correspondences swap between two sets: the pair
      // never met the convergence test and was dropped). Damped the same
      // way, but only after kUndampedEndIterations there, so pairs that
      // converge normally are untouched.
      if (x.dot(prev_step) < -0.5 * x.norm() * prev_step.norm()) damping *= 0.5;
      x *= damping;
      prev_step = x;
    }
    T = motion_exp(x) * T;
    const bool tiny = x.head<3>().norm() < params.convergence_rotation &&
                      x.tail<3>().norm() < params.convergence_translation;
    if (tiny && at_end) {
      small_step = true;
      break;
    }
    // Shrink only once the current distance has settled a little, so a coarse
    // start still pulls the views together before the fine stage.
    if (!at_end && (tiny || x.head<3>().norm() < 1e-3)) d_max = std::max(d_end, d_max * shrink);
    else if (!at_end) d_max = std::max(d_end, d_max * std::sqrt(shrink));
  }
  res.transform = T;
  // Final diagnostics at the fine distance.
  const Normal6 fin = linearise(T, d_end, 1);
  res.queries += fin.queries;
  res.graph_answers += fin.graph_answers;
  res.correspondences = fin.n;
  res.fitness = double(fin.n) / double(source.points.size());
  res.inlier_rmse = fin.n ? std::sqrt(fin.sq_euclid / double(fin.n)) : 0.0;
  res.plane_rmse = fin.n ? std::sqrt(fin.sq_plane / double(fin.n)) : 0.0;
  res.hessian = coloured && lambda > 0 ? Matrix6d(fin.A / lambda) : fin.A;
  if (fin.n < std::size_t(std::max(params.min_correspondences, 6))) {
    res.message = "too few correspondences at the end (" + std::to_string(fin.n) + ")";
  } else if (res.fitness < params.min_fitness) {
    res.message = "overlap too small (fitness " + std::to_string(res.fitness) + " < " +
                  std::to_string(params.min_fitness) + ")";
  } else if (!small_step) {
    // Iteration budget spent: accept when the last steps were already tiny at
    // the fine distance, judged by the current system.
    const double ridge = 1e-9 * fin.A.trace() / 6.0;
    const Vector6d x = (fin.A + ridge * Matrix6d::Identity()).ldlt().solve(-fin.b);
    if (x.allFinite() && x.head<3>().norm() < 1e-4 && x.tail<3>().norm() < 1e-5 * params.units_per_metre) {
      res.converged = true;
    } else {
      res.message = "did not converge in " + std::to_string(params.max_iterations) + " iterations";
    }
  } else {
    res.converged = true;
  }
  return res;
}

}  // namespace station
