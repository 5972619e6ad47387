#include "registration/global_registration.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <set>

#include "registration/icp.h"
#include "core/error.h"
#include "core/sampling.h"
#include "core/kdtree.h"

namespace station {

namespace {

FeatureView finish_view(std::vector<Vec3f> pts, std::vector<Vec3f> normals,
                        const GlobalRegistrationParams& p) {
  FeatureView v;
  // Points whose normal could not be estimated carry no usable descriptor.
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (!(normals[i].squaredNorm() > 0.5f) || !pts[i].allFinite()) continue;
    v.points.push_back(pts[i]);
    v.normals.push_back(normals[i]);
  }
  v.index = std::make_shared<PointIndex>(v.points);
  if (!v.points.empty())
    v.features = compute_fpfh(*v.index, v.normals, p.feature_radius_voxels * p.voxel_size,
                              p.max_feature_neighbors);
  return v;
}

void check_params(const GlobalRegistrationParams& p) {
  if (!(p.voxel_size > 0)) throw InvalidInput("global registration: voxel_size must be positive");
  if (!(p.edge_similarity > 0 && p.edge_similarity <= 1))
    throw InvalidInput("global registration: edge_similarity must be in (0, 1]");
  if (!(p.feature_radius_voxels > 0) || !(p.inlier_distance_voxels > 0))
    throw InvalidInput("global registration: feature radius and inlier distance must be positive");
  if (!(p.colour_gate >= 0) || p.colour_candidates < 1)
    throw InvalidInput("global registration: colour_gate must be >= 0 and colour_candidates >= 1");
}

}  // namespace

FeatureView make_feature_view(const std::vector<Vec3f>& points, const Vec3f& viewpoint,
                              const GlobalRegistrationParams& params) {
  check_params(params);
  std::vector<Vec3f> finite;
  finite.reserve(points.size());
  for (const Vec3f& q : points)
    if (q.allFinite()) finite.push_back(q);
  std::vector<Vec3f> pts = voxel_downsample(finite, params.voxel_size);
  if (pts.size() < 3) return finish_view({}, {}, params);
  const PointIndex index(pts);
  std::vector<Vec3f> normals = pca_normals(index, params.normal_neighbors, viewpoint);
  return finish_view(std::move(pts), std::move(normals), params);
}

FeatureView make_feature_view(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals,
                              const GlobalRegistrationParams& params) {
  check_params(params);
  if (normals.size() != points.size())
    throw InvalidInput("global registration: " + std::to_string(normals.size()) + " normals for " +
                       std::to_string(points.size()) + " points");
  std::vector<Vec3f> finite, fnormals;
  for (std::size_t i = 0; i < points.size(); ++i)
    if (points[i].allFinite() && normals[i].allFinite()) {
      finite.push_back(points[i]);
      fnormals.push_back(normals[i]);
    }
  std::vector<Vec3f> pts = voxel_downsample(finite, params.voxel_size);
  const PointIndex all(finite);
  std::vector<Vec3f> ns(pts.size());
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const auto [j, d] = all.nearest(pts[i]);
    ns[i] = j >= 0 ? fnormals[j].normalized() : Vec3f::Zero();
  }
  return finish_view(std::move(pts), std::move(ns), params);
}

FeatureView with_colours(FeatureView view, const Cloud& coloured) {
  if (!coloured.has_colours() || coloured.empty()) return view;
  const PointIndex index(coloured.points);
  view.chroma.resize(view.points.size());
  for (std::size_t i = 0; i < view.points.size(); ++i) {
    const auto [j, d] = index.nearest(view.points[i]);
    const Rgb& c = coloured.colours[std::size_t(j)];
    const Vec3f rgb(float(c.r), float(c.g), float(c.b));
    view.chroma[i] = rgb / std::max(rgb.sum(), kChromaDark);
  }
  return view;
}

GlobalRegistrationResult register_global(const FeatureView& source, const FeatureView& target,
                                         const GlobalRegistrationParams& p) {
  check_params(p);
  GlobalRegistrationResult res;
  if (source.points.size() < 3 || target.points.size() < 3) {
    res.message = std::string(source.points.size() < 3 ? "source" : "target") +
                  " view has too few feature points";
    return res;
  }
  // Matches: nearest descriptor in both directions (union, deduplicated).
  std::set<std::pair<int, int>> match_set;
  const bool gated = p.colour_gate > 0 && source.chroma.size() == source.points.size() &&
                     target.chroma.size() == target.points.size();
  const std::vector<int> st =
      gated ? nearest_descriptors_gated(source.features, source.chroma, target.features, target.chroma, p.colour_gate,
                                        p.colour_candidates)
            : nearest_descriptors(source.features, target.features);
  const std::vector<int> ts =
      gated ? nearest_descriptors_gated(target.features, target.chroma, source.features, source.chroma, p.colour_gate,
                                        p.colour_candidates)
            : nearest_descriptors(target.features, source.features);
  for (std::size_t i = 0; i < st.size(); ++i)
    if (st[i] >= 0) match_set.insert({int(i), st[i]});
  for (std::size_t j = 0; j < ts.size(); ++j)
    if (ts[j] >= 0) match_set.insert({ts[j], int(j)});
  const std::vector<std::pair<int, int>> matches(match_set.begin(), match_set.end());
  const int m = int(matches.size());
  res.matches = matches.size();
  if (m < 3) {
    res.message = "fewer than 3 feature matches";
    return res;
  }
  std::vector<Vec3d> S(m), T(m), NS(m), NT(m);
  for (int k = 0; k < m; ++k) {
    S[k] = source.points[matches[k].first].cast<double>();
    T[k] = target.points[matches[k].second].cast<double>();
    NS[k] = source.normals[matches[k].first].cast<double>();
    NT[k] = target.normals[matches[k].second].cast<double>();
  }
  const double inlier_d = p.inlier_distance_voxels * p.voxel_size;
  const double inlier_d2 = inlier_d * inlier_d;
  const double min_edge = 2.0 * p.voxel_size;
  const double cos_normal = p.normal_angle_deg > 0 ? std::cos(p.normal_angle_deg * M_PI / 180.0) : -2.0;

  std::mt19937_64 rng(p.seed);
  std::uniform_int_distribution<int> pick(0, m - 1);
  std::vector<GlobalHypothesis> top;
  const int keep = std::max(1, p.hypotheses);
  const auto distinct = [&](const Eigen::Matrix4d& a, const Eigen::Matrix4d& b) {
    return rotation_angle_deg(rigid_inverse(a) * b) > 5.0 ||
           (a.block<3, 1>(0, 3) - b.block<3, 1>(0, 3)).norm() > 2 * p.voxel_size;
  };
  long needed = p.max_iterations;
  int it = 0;
  for (; it < p.max_iterations && it < needed; ++it) {
    const int a = pick(rng), b = pick(rng), c = pick(rng);
    if (a == b || b == c || a == c) continue;
    const int id[3] = {a, b, c};
    bool ok = true;
    for (int e = 0; e < 3 && ok; ++e) {
      const int u = id[e], v = id[(e + 1) % 3];
      const double ls = (S[u] - S[v]).norm(), lt = (T[u] - T[v]).norm();
      if (ls < min_edge || lt < min_edge || std::min(ls, lt) < p.edge_similarity * std::max(ls, lt))
        ok = false;
    }
    if (!ok) {
      ++res.prerejected;
      continue;
    }
    Eigen::Matrix3d src, dst;
    for (int e = 0; e < 3; ++e) {
      src.col(e) = S[id[e]];
      dst.col(e) = T[id[e]];
    }
    const Eigen::Matrix4d X = Eigen::umeyama(src, dst, false);
    if (!X.allFinite()) {
      ++res.prerejected;
      continue;
    }
    const Eigen::Matrix3d R = X.block<3, 3>(0, 0);
    const Vec3d t = X.block<3, 1>(0, 3);
    for (int e = 0; e < 3 && ok; ++e)
      if ((R * NS[id[e]]).dot(NT[id[e]]) < cos_normal) ok = false;
    if (!ok) {
      ++res.prerejected;
      continue;
    }
    int inl = 0;
    double sse = 0;
    for (int k = 0; k < m; ++k) {
      const double d2 = (R * S[k] + t - T[k]).squaredNorm();
      if (d2 < inlier_d2) {
        ++inl;
        sse += d2;
      }
    }
    if (inl < 3) continue;
    GlobalHypothesis h;
    h.transform = X;
    h.inliers = inl;
    h.inlier_rmse = std::sqrt(sse / inl);
    const auto better = [](const GlobalHypothesis& x, const GlobalHypothesis& y) {
      return x.inliers > y.inliers || (x.inliers == y.inliers && x.inlier_rmse < y.inlier_rmse);
    };
    // Replace a similar hypothesis if better, else insert when it makes the top list.
    bool similar = false;
    for (GlobalHypothesis& g : top)
      if (!distinct(g.transform, h.transform)) {
        similar = true;
        if (better(h, g)) g = h;
        break;
      }
    if (!similar) top.push_back(h);
    std::sort(top.begin(), top.end(), better);
    if (int(top.size()) > keep) top.resize(keep);
    // RANSAC stopping rule from the best inlier ratio so far.
    const double w = double(top.front().inliers) / m;
    const double pw = w * w * w;
    if (pw > 1e-12 && pw < 1) {
      const double n_need = std::log(1 - p.confidence) / std::log(1 - pw);
      needed = long(std::min<double>(p.max_iterations, std::ceil(n_need)));
    } else if (pw >= 1) {
      needed = it + 1;
    }
  }
  res.iterations = it;
  res.hypotheses = top;
  if (top.empty() || top.front().inliers < p.min_inliers) {
    res.message = "no consistent feature matches (best " +
                  std::to_string(top.empty() ? 0 : top.front().inliers) + " inliers of " +
                  std::to_string(m) + " matches)";
    return res;
  }
  res.success = true;
  res.transform = top.front().transform;
  return res;
}

}  // namespace station
