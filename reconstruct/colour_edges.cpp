#include "reconstruct/colour_edges.h"

#include <algorithm>
#include <cstdint>
#include <string>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "core/threads.h"
#include "reconstruct/lab.h"

namespace station {

namespace {

std::uint64_t edge_key(int a, int b) {
  const auto lo = std::uint32_t(std::min(a, b)), hi = std::uint32_t(std::max(a, b));
  return (std::uint64_t(lo) << 32) | hi;
}

// One candidate edge u < v: where its colour changes (parameter from u), and the
// vertices inserted there (-1: none).
struct Split {
  std::uint64_t key = 0;
  bool done = false;        // bisected (both ends are the function's colour)
  double t_lo = 0, t_hi = 1;  // bracket of the change: colour of u's side at t_lo, v's at t_hi
  Lab lab_lo{}, lab_hi{};
  int v_lo = -1, v_hi = -1;  // inserted vertex near u / near v
};

// A vertex of a face's polygon, with the side it belongs to along a split edge.
struct Corner {
  int vertex;
  int side;  // index 0..2 of the face corner whose colour it carries
};

}  // namespace

ColourEdgeStats sharpen_colour_edges(Mesh& mesh, const ColourFunction& f, const ColourEdgeParams& params) {
  mesh.check_consistent("colour edges: mesh");
  if (params.steps < 1 || params.steps > 20)
    throw InvalidInput("colour edges: steps must be in [1, 20], got " + std::to_string(params.steps));
  if (!(params.min_difference >= 0) || !(params.end_tolerance >= 0) || params.threads < 0)
    throw InvalidInput("colour edges: min_difference and end_tolerance must be >= 0, threads >= 0");
  ColourEdgeStats stats;
  stats.faces_before = stats.faces_after = mesh.faces.size();
  if (!mesh.has_colours() || mesh.faces.empty()) return stats;
  const double threshold = params.min_difference > 0 ? params.min_difference : f.params().gamma;

  const std::size_t nv = mesh.vertices.size();
  std::vector<Lab> vlab(nv);
  for (std::size_t i = 0; i < nv; ++i) vlab[i] = rgb_to_lab(mesh.colours[i]);

  // Candidate edges: ends more than the threshold apart, each once (sorted keys).
  std::vector<Split> splits;
  for (const Face& face : mesh.faces)
    for (int e = 0; e < 3; ++e) {
      const int a = face[e], b = face[(e + 1) % 3];
      if (delta_e(vlab[std::size_t(a)], vlab[std::size_t(b)]) > threshold && !(params.keep_edge && params.keep_edge(a, b))) {
        Split s;
        s.key = edge_key(a, b);
        splits.push_back(s);
      }
    }
  std::sort(splits.begin(), splits.end(), [](const Split& x, const Split& y) { return x.key < y.key; });
  splits.erase(std::unique(splits.begin(), splits.end(), [](const Split& x, const Split& y) { return x.key == y.key; }),
               splits.end());
  stats.candidate_edges = splits.size();
  if (splits.empty()) return stats;

  // Bisect each: the colour at the midpoint is nearer u's or v's end colour.
  const int threads = worker_threads(std::max(params.threads, 0));
  tbb::task_arena arena(threads);
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, splits.size(), 64), [&](const auto& range) {
      for (std::size_t k = range.begin(); k != range.end(); ++k) {
        Split& s = splits[k];
        const auto u = std::size_t(s.key >> 32), v = std::size_t(s.key & 0xffffffffu);
        const Vec3d pu = mesh.vertices[u].cast<double>(), pv = mesh.vertices[v].cast<double>();
        const Lab cu = f.lab(pu), cv = f.lab(pv);
        if (delta_e(cu, vlab[u]) > params.end_tolerance || delta_e(cv, vlab[v]) > params.end_tolerance) continue;
        double lo = 0, hi = 1;
        Lab llo = cu, lhi = cv;
        for (int step = 0; step < params.steps; ++step) {
          const double m = 0.5 * (lo + hi);
          const Lab cm = f.lab(pu + m * (pv - pu));
          if (delta_e(cm, cu) <= delta_e(cm, cv)) {
            lo = m;
            llo = cm;
          } else {
            hi = m;
            lhi = cm;
          }
        }
        s.done = true;
        s.t_lo = lo;
        s.t_hi = hi;
        s.lab_lo = llo;
        s.lab_hi = lhi;
      }
    });
  });

  // New vertices, in edge order (deterministic).
  const bool normals = mesh.has_normals();
  // Appends a vertex; its normal is `normal` normalised (that of vertex `fallback`
  // when it is zero).
  auto append = [&](const Vec3f& p, const Rgb& colour, const Vec3f& normal, std::size_t fallback) {
    mesh.vertices.push_back(p);
    mesh.colours.push_back(colour);
    if (normals) {
      const float len = normal.norm();
      mesh.normals.push_back(len > 0 ? Vec3f(normal / len) : mesh.normals[fallback]);
    }
    ++stats.new_vertices;
    return int(mesh.vertices.size() - 1);
  };
  auto add_vertex = [&](std::size_t u, std::size_t v, double t, const Lab& lab) {
    const float w = float(t);
    const Vec3f n = normals ? Vec3f((1 - w) * mesh.normals[u] + w * mesh.normals[v]) : Vec3f::Zero();
    return append(mesh.vertices[u] + w * (mesh.vertices[v] - mesh.vertices[u]), lab_to_rgb(lab), n, u);
  };
  for (Split& s : splits) {
    if (!s.done) continue;
    ++stats.split_edges;
    const auto u = std::size_t(s.key >> 32), v = std::size_t(s.key & 0xffffffffu);
    if (s.t_lo > 0) s.v_lo = add_vertex(u, v, s.t_lo, s.lab_lo);
    if (s.t_hi < 1) s.v_hi = add_vertex(u, v, s.t_hi, s.lab_hi);
  }
  if (stats.split_edges == 0) return stats;

  auto find = [&](int a, int b) -> const Split* {
    const std::uint64_t key = edge_key(a, b);
    auto it = std::lower_bound(splits.begin(), splits.end(), key,
                               [](const Split& s, std::uint64_t k) { return s.key < k; });
    return it != splits.end() && it->key == key && it->done ? &*it : nullptr;
  };

  // Re-triangulate the faces that touch a split edge.
  std::vector<Face> out;
  out.reserve(mesh.faces.size() + 4 * stats.split_edges);
  std::vector<Corner> poly;
  for (const Face& face : mesh.faces) {
    const Split* edge[3];
    int split_count = 0;
    for (int e = 0; e < 3; ++e) {
      edge[e] = find(face[e], face[(e + 1) % 3]);
      split_count += edge[e] != nullptr;
    }
    if (split_count == 0) {
      out.push_back(face);
      continue;
    }
    // The face's polygon, counter-clockwise: corner e, then the points on edge e
    // (corner e -> corner e+1) in that order, each tagged with the corner whose side
    // of the colour change it lies on.
    poly.clear();
    for (int e = 0; e < 3; ++e) {
      poly.push_back(Corner{face[e], e});
      const Split* s = edge[e];
      if (!s) continue;
      const int next = (e + 1) % 3;
      const bool forward = face[e] < face[next];  // the split's u is this corner
      const int near_this = forward ? s->v_lo : s->v_hi, near_next = forward ? s->v_hi : s->v_lo;
      if (near_this >= 0) poly.push_back(Corner{near_this, e});
      if (near_next >= 0) poly.push_back(Corner{near_next, next});
    }
    const int n = int(poly.size());
    auto emit = [&](const Corner& a, const Corner& b, const Corner& c) { out.push_back(Face(a.vertex, b.vertex, c.vertex)); };
    if (split_count == 1) {
      // Fan from the corner opposite the split edge (edge e runs corner e -> e+1).
      int split_edge = 0;
      for (int e = 0; e < 3; ++e)
        if (edge[e]) split_edge = e;
      const int apex = face[(split_edge + 2) % 3];
      int start = 0;
      for (int i = 0; i < n; ++i)
        if (poly[std::size_t(i)].vertex == apex) start = i;
      for (int i = 1; i + 1 < n; ++i)
        emit(poly[std::size_t(start)], poly[std::size_t((start + i) % n)], poly[std::size_t((start + i + 1) % n)]);
    } else if (split_count == 2) {
      // The odd corner shares both split edges; its side is one run of the polygon,
      // the other two corners' the other. Each run is fanned, and the strip between
      // them (the only faces that cross the change) joins the runs' ends.
      int unsplit = 0;
      for (int e = 0; e < 3; ++e)
        if (!edge[e]) unsplit = e;
      const int odd = (unsplit + 2) % 3;
      // Rotate so that the odd side's run comes first.
      int start = -1;
      for (int i = 0; i < n; ++i) {
        const bool mine = poly[std::size_t(i)].side == odd;
        const bool prev_mine = poly[std::size_t((i + n - 1) % n)].side == odd;
        if (mine && !prev_mine) start = i;
      }
      std::vector<Corner> run_a, run_b;
      for (int i = 0; i < n; ++i) {
        const Corner& c = poly[std::size_t((start + i) % n)];
        (c.side == odd ? run_a : run_b).push_back(c);
      }
      for (std::size_t i = 1; i + 1 < run_a.size(); ++i) emit(run_a[0], run_a[i], run_a[i + 1]);
      for (std::size_t i = 1; i + 1 < run_b.size(); ++i) emit(run_b[0], run_b[i], run_b[i + 1]);
      // The strip is the quad (A_last, B_first, B_last, A_first), cut along a diagonal
      // that does not join two points of the same edge: when A_last is the odd corner
      // itself, B_last and A_first lie on one of its edges with it.
      const Corner &al = run_a.back(), &af = run_a.front(), &bf = run_b.front(), &bl = run_b.back();
      if (run_a.size() == 1) {
        emit(al, bf, bl);
      } else if (al.vertex == face[odd]) {
        emit(al, bf, af);
        emit(bf, bl, af);
      } else {
        emit(al, bf, bl);
        emit(al, bl, af);
      }
    } else {
      // Three colours meet: fan around a new vertex at the centroid.
      const Vec3f centre = (mesh.vertices[std::size_t(face[0])] + mesh.vertices[std::size_t(face[1])] +
                            mesh.vertices[std::size_t(face[2])]) /
                           3.f;
      Vec3f normal_sum = Vec3f::Zero();
      if (normals)
        normal_sum = mesh.normals[std::size_t(face[0])] + mesh.normals[std::size_t(face[1])] +
                     mesh.normals[std::size_t(face[2])];
      const int middle = append(centre, f.rgb(centre.cast<double>()), normal_sum, std::size_t(face[0]));
      ++stats.three_way_faces;
      const Corner c{middle, -1};
      for (int i = 0; i < n; ++i) emit(c, poly[std::size_t(i)], poly[std::size_t((i + 1) % n)]);
    }
  }
  mesh.faces = std::move(out);
  stats.faces_after = mesh.faces.size();
  return stats;
}

}  // namespace station
