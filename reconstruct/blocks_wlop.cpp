#include "reconstruct/blocks_wlop.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/threads.h"

namespace station {

namespace {

// consolidate()'s area estimate over `of` (indices into points): each point stands for
// pi rho^2 / 15, rho the distance to its 16th nearest in `index` (itself counted).
double area_of(const PointIndex& index, const std::vector<Vec3f>& points, const std::vector<std::size_t>& of,
               int threads) {
  constexpr int kNearest = 16;
  std::vector<double> a(of.size(), 0.0);
  tbb::task_arena arena(worker_threads(threads));
  arena.execute([&] {
    tbb::parallel_for(std::size_t(0), of.size(), [&](std::size_t t) {
      const auto k = index.knn(points[of[t]], kNearest);
      if (!k.empty()) a[t] = M_PI * double(k.back().second) * double(k.back().second) / (kNearest - 1);
    });
  });
  double sum = 0;
  for (double x : a) sum += x;
  return sum;
}

// The points a WLOP block may hold within max_bytes (its margin included).
double block_capacity(double max_bytes) { return (max_bytes - kWlopBaseBytes) / kWlopBytesPerPoint; }

}  // namespace

int wlop_block_count(std::size_t points, int blocks, double max_bytes) {
  if (blocks < 0) throw InvalidInput("consolidate: blocks must be auto (0) or a count");
  if (blocks > 0) return blocks;
  std::size_t n = std::max<std::size_t>(1, (points + kAutoWlopBlockPoints - 1) / kAutoWlopBlockPoints);
  if (max_bytes > 0) {
    const double fit = block_capacity(max_bytes) / (4.0 / 3.0);  // a box's points, its margin a third more
    if (!(fit >= 100000))
      throw InvalidInput("consolidate: --max-memory " + std::to_string(max_bytes / 1e9).substr(0, 4) +
                         " GB cannot hold a WLOP block of 100,000 points (about " +
                         std::to_string((kWlopBaseBytes + 100000 * kWlopBytesPerPoint * 4 / 3) / 1e9).substr(0, 4) +
                         " GB)");
    n = std::max(n, std::size_t(std::ceil(double(points) / fit)));
  }
  return int(std::min<std::size_t>(n, 4096));
}

std::size_t count_points(const CloudSource& source) {
  std::size_t n = 0;
  source([&](const Cloud& c) { n += c.size(); });
  return n;
}

int wlop_block_of(const BlockGrid& grid, const Vec3f& x) {
  int ijk[3];
  for (int a = 0; a < 3; ++a) {
    const double t = std::floor((double(x[a]) - grid.lattice.origin[a]) / grid.lattice.h);
    ijk[a] = int(std::clamp(t, 0.0, double(grid.lattice.global_cells[std::size_t(a)] - 1)));
  }
  return grid.owner(ijk[0], ijk[1], ijk[2]);
}

ConsolidationPlan plan_consolidation(const CloudSource& source, const WlopParams& params, int blocks,
                                     double max_bytes) {
  if (blocks < 0) throw InvalidInput("consolidate: blocks must be auto (0) or a count");
  const bool automatic = blocks == 0;
  ConsolidationPlan plan;
  bool finite = true;
  source([&](const Cloud& c) {
    for (const Vec3f& q : c.points) {
      if (!q.allFinite()) {
        finite = false;
        continue;
      }
      if (plan.points++ == 0) plan.bounds.min = plan.bounds.max = q;
      plan.bounds.min = plan.bounds.min.cwiseMin(q);
      plan.bounds.max = plan.bounds.max.cwiseMax(q);
    }
  });
  if (!finite) throw InvalidInput("consolidate: input has non-finite coordinates");
  if (plan.points == 0) throw InvalidInput("consolidate: empty input");
  plan.diagonal = (plan.bounds.max.cast<double>() - plan.bounds.min.cast<double>()).norm();
  if (!(plan.diagonal > 0)) throw InvalidInput("consolidate: all input points coincide (zero bounding box)");
  if (!(params.radius >= 0) || !std::isfinite(params.radius))
    throw InvalidInput("consolidate: radius must be >= 0 and finite");
  check_radii_within(params, plan.diagonal);  // before the blocks' margins are planned from them
  plan.radius = params.radius > 0 ? params.radius : 4.0 * plan.diagonal / std::sqrt(double(plan.points));
  plan.output_points = std::min(wlop_requested_points(plan.points, params), plan.points);
  blocks = wlop_block_count(plan.points, blocks, max_bytes);
  // The points of each box (with kProjection, on the first pass, the area's every k-th
  // point). With a memory bound, more blocks while the largest box (a third more for
  // its margin) does not fit: boxes are not even.
  const std::size_t every = std::max<std::size_t>(1, plan.points / 200000);
  std::vector<Vec3f> summary;
  for (bool first = true;; first = false) {
    plan.grid = plan_blocks(plan.bounds, 1024, blocks, kWlopMarginRadii * plan.radius);
    plan.box_points.assign(std::size_t(plan.grid.size()), 0);
    std::size_t index = 0;
    source([&](const Cloud& c) {
      for (const Vec3f& q : c.points) {
        if (!q.allFinite()) continue;
        ++plan.box_points[std::size_t(wlop_block_of(plan.grid, q))];
        if (first && params.attraction == WlopAttraction::kProjection && index++ % every == 0) summary.push_back(q);
      }
    });
    if (!automatic || !(max_bytes > 0) || blocks >= 4096) break;
    const double largest = double(*std::max_element(plan.box_points.begin(), plan.box_points.end())) * 4 / 3;
    const double fit = block_capacity(max_bytes);
    if (largest <= fit) break;
    blocks = int(std::min(4096.0, std::ceil(double(blocks) * largest / fit) + 1));
  }
  if (!summary.empty()) {
    std::vector<std::size_t> all(summary.size());
    for (std::size_t i = 0; i < all.size(); ++i) all[i] = i;
    const PointIndex si(summary);
    plan.area = area_of(si, summary, all, params.threads);
  }
  return plan;
}

Cloud consolidate_block(const Cloud& points, const ConsolidationPlan& plan, int id, const WlopParams& params,
                        WlopResult* diagnostics) {
  if (id < 0 || id >= plan.grid.size()) throw InvalidInput("consolidate_block: no block " + std::to_string(id));
  Cloud out;
  // Its share of |I| in its box, and what that asks of its region (box and margin).
  std::vector<std::size_t> box, region(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    region[i] = i;
    if (wlop_block_of(plan.grid, points.points[i]) == id) box.push_back(i);
  }
  if (box.empty() || plan.output_points == 0) return out;
  double want_box = 0, scale = 0;
  if (params.attraction == WlopAttraction::kProjection && plan.area > 0) {
    const PointIndex index(points.points);
    const double a_box = area_of(index, points.points, box, params.threads);
    const double a_region = area_of(index, points.points, region, params.threads);
    want_box = double(plan.output_points) * a_box / plan.area;
    scale = a_box > 0 ? a_region / a_box : 1;
  } else {
    want_box = double(plan.output_points) * double(plan.box_points[std::size_t(id)]) / double(plan.points);
    scale = double(points.size()) / double(box.size());
  }
  const std::size_t want = std::size_t(std::llround(want_box * scale));
  if (want == 0) return out;
  WlopParams p = params;
  p.target_points = want;
  p.min_points = p.max_points = 0;
  p.radius = plan.radius;
  p.frame_diagonal = plan.diagonal;
  p.frame_points = plan.points;
  WlopResult r = consolidate(points, p);
  const bool normals = r.cloud.has_normals(), colours = r.cloud.has_colours();
  for (std::size_t i = 0; i < r.cloud.size(); ++i) {
    if (wlop_block_of(plan.grid, r.cloud.points[i]) != id) continue;
    out.points.push_back(r.cloud.points[i]);
    if (normals) out.normals.push_back(r.cloud.normals[i]);
    if (colours) out.colours.push_back(r.cloud.colours[i]);
  }
  if (diagnostics) {
    r.cloud = Cloud{};
    r.positions.clear();
    *diagnostics = std::move(r);
  }
  return out;
}

void append_block_output(Cloud& to, const Cloud& part, const std::string& what) {
  if (part.empty()) return;
  if (!to.empty() && (to.has_normals() != part.has_normals() || to.has_colours() != part.has_colours()))
    throw FormatError(what + ": its attributes (normals, colours) differ from the other blocks'");
  to.points.insert(to.points.end(), part.points.begin(), part.points.end());
  to.normals.insert(to.normals.end(), part.normals.begin(), part.normals.end());
  to.colours.insert(to.colours.end(), part.colours.begin(), part.colours.end());
}

Cloud consolidate_blocks(const CloudSource& source, const WlopParams& params, int blocks, BlockWlopStats* stats,
                         const std::function<void(const std::string&)>& note, double max_bytes) {
  const auto t0 = std::chrono::steady_clock::now();
  const ConsolidationPlan plan = plan_consolidation(source, params, blocks, max_bytes);
  BlockWlopStats st;
  st.blocks = plan.grid.size();
  Cloud out;
  for (int id = 0; id < plan.grid.size(); ++id) {
    const Cloud pts = block_points(source, plan.grid, id);
    st.max_block_points = std::max(st.max_block_points, pts.size());
    const Cloud part = consolidate_block(pts, plan, id, params);
    append_block_output(out, part, "consolidate: block " + std::to_string(id + 1));
    if (note) {
      char line[160];
      std::snprintf(line, sizeof line, "block %d/%d: %zu points -> %zu", id + 1, plan.grid.size(), pts.size(), part.size());
      note(line);
    }
  }
  st.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (stats) *stats = st;
  return out;
}

}  // namespace station
