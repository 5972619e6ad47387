#include "reconstruct/blocks.h"

#include <fcntl.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <numeric>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "core/threads.h"
#include "core/union_find.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/colour_transfer.h"
#include "reconstruct/half_space_clip.h"
#include "reconstruct/mesh_clean.h"
#include "reconstruct/mpu.h"
#include "reconstruct/colour_edges.h"
#include "reconstruct/winding_close.h"

namespace station {

namespace {

using Clock = std::chrono::steady_clock;

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

bool inside(const Aabb& box, const Vec3f& p) {
  return (p.array() >= box.min.array()).all() && (p.array() <= box.max.array()).all();
}

void append(Cloud& to, const Cloud& from, std::size_t i) {
  to.points.push_back(from.points[i]);
  if (from.has_normals()) to.normals.push_back(from.normals[i]);
  if (from.has_colours()) to.colours.push_back(from.colours[i]);
}

// f = v everywhere (a block without enough points to fit: outside).
struct Constant : ImplicitFunction {
  double v = 0;
  double value(const Vec3d&) const override { return v; }
  Vec3d gradient(const Vec3d&) const override { return Vec3d::Zero(); }
};

// Mean nearest-neighbour distance and median of r_8 sqrt(pi / 8) (MpuDiagnostics),
// over the points `of` (indices into the indexed points).
std::pair<double, double> spacings(const PointIndex& index, const std::vector<Vec3f>& points,
                                   const std::vector<std::size_t>& of) {
  constexpr int kNeighbours = 8;
  std::vector<double> nnd(of.size()), density(of.size());
  tbb::parallel_for(std::size_t(0), of.size(), [&](std::size_t t) {
    const auto k = index.knn(points[of[t]], kNeighbours + 1);
    nnd[t] = k.size() > 1 ? k[1].second : 0;
    density[t] = k.size() > std::size_t(kNeighbours) ? k[kNeighbours].second * std::sqrt(M_PI / kNeighbours) : 0;
  });
  if (of.empty()) return {0, 0};
  double sum = 0;
  for (double d : nnd) sum += d;
  std::nth_element(density.begin(), density.begin() + long(density.size() / 2), density.end());
  return {sum / double(nnd.size()), density[density.size() / 2]};
}

}  // namespace

// ------------------------------------------------------------------ the grid

std::array<int, 3> BlockGrid::coords(int id) const {
  return {id % counts[0], id / counts[0] % counts[1], id / (counts[0] * counts[1])};
}

LatticeWindow BlockGrid::window(int id) const {
  const auto c = coords(id);
  LatticeWindow w = lattice;
  for (std::size_t a = 0; a < 3; ++a) {
    w.offset[a] = splits[a][std::size_t(c[a])];
    w.cells[a] = splits[a][std::size_t(c[a]) + 1] - w.offset[a];
  }
  return w;
}

Aabb BlockGrid::region(int id) const {
  const LatticeWindow w = window(id);
  Aabb box;
  for (int a = 0; a < 3; ++a) {
    const double lo = lattice.origin[a] + lattice.h * w.offset[std::size_t(a)] - margin;
    const double hi = lattice.origin[a] + lattice.h * (w.offset[std::size_t(a)] + w.cells[std::size_t(a)]) + margin;
    box.min[a] = float(lo);
    box.max[a] = float(hi);
  }
  return box;
}

bool BlockGrid::seam_plane(int a, int index) const {
  const auto& s = splits[std::size_t(a)];
  if (index <= 0 || index >= s.back()) return false;
  return std::binary_search(s.begin(), s.end(), index);
}

bool BlockGrid::on_seam(std::uint64_t edge) const {
  const int ijk[3] = {int(edge & 0xFFFFF), int(edge >> 20 & 0xFFFFF), int(edge >> 40 & 0xFFFFF)};
  const int axis = int(edge >> 60);
  for (int a = 0; a < 3; ++a)
    if (a != axis && seam_plane(a, ijk[a])) return true;
  return false;
}

int BlockGrid::owner(int i, int j, int k) const {
  const int ijk[3] = {i, j, k};
  int c[3];
  for (int a = 0; a < 3; ++a) {
    const auto& s = splits[std::size_t(a)];
    // The last split at or below the index (the global end plane: the last block).
    const auto it = std::upper_bound(s.begin(), s.end(), ijk[a]);
    c[a] = std::clamp(int(it - s.begin()) - 1, 0, counts[std::size_t(a)] - 1);
  }
  return id(c[0], c[1], c[2]);
}

BlockGrid plan_blocks(const Aabb& box, int resolution, int blocks, double margin) {
  if (!box.valid() || !all_finite({box.min, box.max})) throw InvalidInput("plan_blocks: invalid bounding box");
  if (resolution < 1 || resolution >= (1 << 20)) throw InvalidInput("plan_blocks: resolution must be in [1, 2^20)");
  if (blocks < 1) throw InvalidInput("plan_blocks: at least one block");
  if (!(margin >= 0) || !std::isfinite(margin)) throw InvalidInput("plan_blocks: the margin must be >= 0");
  const Vec3d ext = (box.max - box.min).cast<double>();
  if (!(ext.maxCoeff() > 0)) throw InvalidInput("plan_blocks: degenerate bounding box");
  BlockGrid g;
  g.lattice.origin = box.min.cast<double>();
  g.lattice.h = ext.maxCoeff() / resolution;
  for (std::size_t a = 0; a < 3; ++a) {
    g.lattice.global_cells[a] = std::max(1, int(std::ceil(ext[int(a)] / g.lattice.h - 1e-9)));
    g.lattice.cells[a] = g.lattice.global_cells[a];
  }
  // Grow the count along the axis whose blocks are longest while the total stays
  // within `blocks` (and a block keeps at least 4 cells).
  for (;;) {
    int best = -1;
    double longest = 0;
    for (int a = 0; a < 3; ++a) {
      const int c = g.counts[std::size_t(a)];
      const double side = double(g.lattice.global_cells[std::size_t(a)]) / c;
      const int total = g.size() / c * (c + 1);
      if (total > blocks || g.lattice.global_cells[std::size_t(a)] / (c + 1) < 4) continue;
      if (side > longest) longest = side, best = a;
    }
    if (best < 0) break;
    ++g.counts[std::size_t(best)];
  }
  for (std::size_t a = 0; a < 3; ++a) {
    const int n = g.lattice.global_cells[a], c = g.counts[a];
    g.splits[a].resize(std::size_t(c) + 1);
    for (int t = 0; t <= c; ++t) g.splits[a][std::size_t(t)] = int(std::lround(double(n) * t / c));
  }
  g.margin = margin;
  return g;
}

std::vector<int> block_order(const BlockGrid& grid) {
  std::vector<int> order;
  for (int bk = grid.counts[2] - 1; bk >= 0; --bk)
    for (int bj = grid.counts[1] - 1; bj >= 0; --bj)
      for (int bi = grid.counts[0] - 1; bi >= 0; --bi) order.push_back(grid.id(bi, bj, bk));
  return order;
}

int block_wave(const BlockGrid& grid, int id) {
  const auto c = grid.coords(id);
  return (grid.counts[0] - 1 - c[0]) + (grid.counts[1] - 1 - c[1]) + (grid.counts[2] - 1 - c[2]);
}

// ------------------------------------------------------------------ seam values

const double* SeamValues::lookup(const Vec3d& x) const {
  if (table_.empty()) return nullptr;
  const Vec3d g = (x - origin_) / h_;
  int ijk[3];
  for (int a = 0; a < 3; ++a) {
    const double r = std::round(g[a]);
    if (!(std::abs(g[a] - r) <= 1e-6) || r < 0 || r >= double(1 << 20)) return nullptr;
    ijk[a] = int(r);
  }
  const auto it = table_.find(lattice_point_key(ijk[0], ijk[1], ijk[2]));
  return it == table_.end() ? nullptr : &it->second;
}

double SeamValues::value(const Vec3d& x) const {
  const double* v = lookup(x);
  return v ? *v : f_.value(x);
}

void SeamValues::values_near(const Vec3d* xs, int n, double* out) const {
  f_.values_near(xs, n, out);
  for (int i = 0; i < n; ++i)
    if (const double* v = lookup(xs[i])) out[i] = *v;
}

void SeamValues::values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
  f_.values_gradients_near(xs, n, values, grads);
  for (int i = 0; i < n; ++i)
    if (const double* v = lookup(xs[i])) values[i] = *v;
}

SeamTable lower_face_values(const ImplicitFunction& f, const BlockGrid& grid, int id, int threads) {
  const LatticeWindow w = grid.window(id);
  const auto& o = w.offset;
  const auto& c = w.cells;
  // The owned points (half-open window) with an index on a lower face shared with a
  // block below (not the global 0 planes).
  std::vector<std::array<int, 3>> pts;
  const int end[3] = {o[0] + c[0] + (o[0] + c[0] == w.global_cells[0]), o[1] + c[1] + (o[1] + c[1] == w.global_cells[1]),
                      o[2] + c[2] + (o[2] + c[2] == w.global_cells[2])};
  const bool lower[3] = {o[0] > 0, o[1] > 0, o[2] > 0};
  for (int k = o[2]; k < end[2]; ++k)
    for (int j = o[1]; j < end[1]; ++j) {
      if ((lower[1] && j == o[1]) || (lower[2] && k == o[2])) {
        for (int i = o[0]; i < end[0]; ++i) pts.push_back({i, j, k});
      } else if (lower[0]) {
        pts.push_back({o[0], j, k});
      }
    }
  // Rows of 8 points along x (close together: values_near shares the walk).
  std::vector<double> vals(pts.size());
  tbb::task_arena arena(worker_threads(threads));
  const std::size_t runs = (pts.size() + 7) / 8;
  arena.execute([&] {
    tbb::parallel_for(std::size_t(0), runs, [&](std::size_t r) {
      Vec3d xs[8];
      const std::size_t first = 8 * r, count = std::min<std::size_t>(8, pts.size() - first);
      for (std::size_t t = 0; t < count; ++t) {
        const auto& p = pts[first + t];
        xs[t] = w.origin + w.h * Vec3d(p[0], p[1], p[2]);
      }
      f.values_near(xs, int(count), vals.data() + first);
    });
  });
  SeamTable table;
  table.reserve(pts.size());
  for (std::size_t t = 0; t < pts.size(); ++t) table.emplace(lattice_point_key(pts[t][0], pts[t][1], pts[t][2]), vals[t]);
  return table;
}

// ------------------------------------------------------------------ the summary

CloudSource memory_source(const Cloud& cloud) {
  return [&cloud](const std::function<void(const Cloud&)>& chunk) { chunk(cloud); };
}

BlockSummary summarise_cloud(const CloudSource& source, const SurfaceParams& p) {
  BlockSummary s;
  bool normals = true, colours = true, finite = true;
  source([&](const Cloud& c) {
    s.points += c.size();
    if (!c.empty()) {
      normals = normals && c.has_normals();
      colours = colours && c.has_colours();
    }
    for (const Vec3f& q : c.points) {
      finite = finite && q.allFinite();
      s.bounds.extend(q);
    }
  });
  if (s.points == 0) throw InvalidInput("blocks: the cloud is empty");
  if (!finite) throw InvalidInput("blocks: the cloud has non-finite coordinates");
  if (!normals)
    throw InvalidInput("blocks need oriented normals (each block alone cannot orient them consistently): "
                       "estimate them first (station consolidate) or run without --blocks");
  s.colours = colours;
  s.every = std::max<std::size_t>(1, s.points / kSummaryPoints);
  std::size_t index = 0;
  source([&](const Cloud& c) {
    for (std::size_t i = 0; i < c.size(); ++i, ++index)
      if (index % s.every == 0) append(s.far_field, c, i);
  });
  s.far_field.colours.clear();

  // Spacings at full density: exact on the summary when it is the cloud, else on
  // full-density patches around evenly spread summary points.
  const PointIndex sindex(s.far_field.points);
  std::vector<std::size_t> all(s.far_field.size());
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = i;
  tbb::task_arena arena(worker_threads(p.threads));
  arena.execute([&] {
    auto [mean, sample] = spacings(sindex, s.far_field.points, all);
    if (s.every > 1) {
      constexpr int kPatches = 32;
      constexpr double kPatchPoints = 3000;
      const double thin = std::sqrt(double(s.every));
      const double radius = std::sqrt(kPatchPoints / M_PI) * sample / thin;
      std::vector<Vec3f> centres;
      for (int t = 0; t < kPatches; ++t) centres.push_back(s.far_field.points[s.far_field.size() * std::size_t(t) / kPatches]);
      const PointIndex cindex(centres);
      std::vector<Vec3f> patch;
      std::vector<int> patch_of;
      source([&](const Cloud& c) {
        for (const Vec3f& q : c.points) {
          const auto [ci, d] = cindex.nearest(q);
          if (ci >= 0 && d <= radius) patch.push_back(q), patch_of.push_back(ci);
        }
      });
      // Statistics over the patches' inner halves (their neighbours all collected).
      const PointIndex pindex(patch);
      std::vector<std::size_t> inner;
      for (std::size_t i = 0; i < patch.size(); ++i)
        if ((patch[i] - centres[std::size_t(patch_of[i])]).norm() <= 0.5 * radius) inner.push_back(i);
      if (inner.size() >= 100) std::tie(mean, sample) = spacings(pindex, patch, inner);
      else mean /= thin, sample /= thin;
    }
    s.mean_spacing = mean;
    s.sample_spacing = sample;
  });

  s.hole = p.hole;
  if (p.hole == HoleMode::kAuto) {
    s.enclosure = cloud_enclosure(s.far_field);
    if (*s.enclosure <= -kEnclosedAbove) {
      s.flip_normals = true;
      for (Vec3f& n : s.far_field.normals) n = -n;
      s.enclosure = -*s.enclosure;
    }
    s.hole = *s.enclosure >= kEnclosedAbove ? HoleMode::kClose : HoleMode::kKeep;
  }
  s.epsilon0 = p.epsilon0 > 0 ? p.epsilon0 : std::max(MpuParams().epsilon0, surface_epsilon0(s.far_field));
  s.box = s.bounds;
  const float pad = 0.05f * (s.box.max - s.box.min).maxCoeff();
  s.box.min.array() -= pad;
  s.box.max.array() += pad;
  const double longest = double((s.box.max - s.box.min).maxCoeff());
  s.resolution_auto = p.resolution <= 0;
  s.resolution = s.resolution_auto ? auto_resolution(longest, s.sample_spacing > 0 ? s.sample_spacing : s.mean_spacing)
                                   : p.resolution;
  if (s.hole == HoleMode::kClose && p.table_up && p.table_up->norm() > 0) {
    const Vec3d u = p.table_up->normalized();
    double lowest = std::numeric_limits<double>::infinity();
    source([&](const Cloud& c) {
      for (const Vec3f& q : c.points) lowest = std::min(lowest, u.dot(q.cast<double>()));
    });
    s.table_height = lowest;
  }
  return s;
}

double block_margin(const BlockSummary& s, double cell) {
  return std::max((s.hole == HoleMode::kKeep ? kKeepMarginCells : kMarginCells) * cell, 8 * s.mean_spacing);
}

Cloud block_points(const CloudSource& source, const BlockGrid& grid, int id) {
  const Aabb region = grid.region(id);
  Cloud out;
  source([&](const Cloud& c) {
    for (std::size_t i = 0; i < c.size(); ++i)
      if (inside(region, c.points[i])) append(out, c, i);
  });
  return out;
}

// A bucket file: a header (magic, then the block's region as 6 floats), chunks of
// [u32 count > 0][u8 flags: 1 normals, 2 colours][count points as 3 floats][normals, 3
// floats each][colours, 3 bytes each], then a trailer [u32 0xFFFFFFFF][u64 points in
// all]; native byte order (the file lives in a run's work folder, read back on the same
// machines). The region says which grid the points were sorted for; the trailer that
// the file is whole.
namespace {

constexpr char kBucketMagic[8] = {'S', 'T', 'B', 'U', 'C', 'K', '2', '\n'};
constexpr std::uint32_t kBucketEnd = 0xFFFFFFFFu;
constexpr std::size_t kBucketHeader = sizeof kBucketMagic + 6 * sizeof(float);

static_assert(sizeof(Vec3f) == 12 && sizeof(Rgb) == 3, "bucket records are packed");

void check_written(std::ofstream& out, const std::string& path) {
  out.close();
  if (!out) throw IoError("writing " + path + " failed: " + std::strerror(errno));
}

// Appends a chunk (`region`: a new file, with the header first).
void write_chunk(const Cloud& c, const std::string& path, const Aabb* region) {
  std::ofstream out(path, std::ios::binary | (region ? std::ios::trunc : std::ios::app));
  if (region) {
    out.write(kBucketMagic, sizeof kBucketMagic);
    out.write(reinterpret_cast<const char*>(region->min.data()), 12);
    out.write(reinterpret_cast<const char*>(region->max.data()), 12);
  }
  if (!c.empty()) {
    const std::uint32_t n = std::uint32_t(c.size());
    const std::uint8_t flags = std::uint8_t((c.has_normals() ? 1 : 0) | (c.has_colours() ? 2 : 0));
    out.write(reinterpret_cast<const char*>(&n), sizeof n);
    out.write(reinterpret_cast<const char*>(&flags), 1);
    for (const Vec3f& p : c.points) out.write(reinterpret_cast<const char*>(p.data()), 12);
    for (const Vec3f& p : c.normals) out.write(reinterpret_cast<const char*>(p.data()), 12);
    for (const Rgb& k : c.colours) out.write(reinterpret_cast<const char*>(&k), 3);
  }
  check_written(out, path);
}

// The trailer, then the file flushed to the disk (before the rename publishes it).
void write_trailer(const std::string& path, std::uint64_t total) {
  std::ofstream out(path, std::ios::binary | std::ios::app);
  out.write(reinterpret_cast<const char*>(&kBucketEnd), sizeof kBucketEnd);
  out.write(reinterpret_cast<const char*>(&total), sizeof total);
  check_written(out, path);
  const int fd = ::open(path.c_str(), O_RDONLY);
  const bool synced = fd >= 0 && ::fsync(fd) == 0;
  const int err = errno;
  if (fd >= 0) ::close(fd);
  if (!synced) throw IoError("writing " + path + " failed: " + std::strerror(err));
}

}  // namespace

namespace {

// Whether a bucket file's first kBucketHeader bytes are a header, for `region` when given.
bool header_matches(const char* head, const Aabb* region) {
  if (std::memcmp(head, kBucketMagic, sizeof kBucketMagic) != 0) return false;
  if (!region) return true;
  Aabb stored;
  std::memcpy(stored.min.data(), head + sizeof kBucketMagic, 12);
  std::memcpy(stored.max.data(), head + sizeof kBucketMagic + 12, 12);
  return stored.min == region->min && stored.max == region->max;
}

}  // namespace

bool bucket_matches(const std::string& path, const Aabb& region) {
  std::ifstream in(path, std::ios::binary);
  char head[kBucketHeader];
  return in.read(head, std::streamsize(sizeof head)) && header_matches(head, &region);
}

void bucket_points(const CloudSource& source, const BlockGrid& grid, const std::vector<int>& ids,
                   const std::function<std::string(int)>& path, std::size_t flush_points) {
  std::vector<int> slot(std::size_t(grid.size()), -1);
  for (std::size_t k = 0; k < ids.size(); ++k) {
    if (ids[k] < 0 || ids[k] >= grid.size() || slot[std::size_t(ids[k])] >= 0)
      throw InvalidInput("bucket_points: block ids must be distinct and in [0, " + std::to_string(grid.size()) + ")");
    slot[std::size_t(ids[k])] = int(k);
  }
  if (ids.empty()) return;
  // Per axis, each block index's span of its region (the same floats as region()).
  std::array<std::vector<std::pair<float, float>>, 3> span;
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < grid.counts[std::size_t(a)]; ++b) {
      std::array<int, 3> c{0, 0, 0};
      c[std::size_t(a)] = b;
      const Aabb r = grid.region(grid.id(c[0], c[1], c[2]));
      span[std::size_t(a)].emplace_back(r.min[a], r.max[a]);
    }
  // Buffered points a block before it appends them: flush_points, fewer when many blocks
  // would together hold more than kBucketBufferPoints.
  const std::size_t limit =
      std::max<std::size_t>(1024, std::min(flush_points, kBucketBufferPoints / ids.size()));
  std::vector<Cloud> buffer(ids.size());
  std::vector<std::string> part(ids.size());
  std::vector<std::uint64_t> total(ids.size(), 0);
  for (std::size_t k = 0; k < ids.size(); ++k) part[k] = path(ids[k]) + ".part";
  try {
    for (std::size_t k = 0; k < ids.size(); ++k) {
      const Aabb region = grid.region(ids[k]);
      write_chunk(Cloud{}, part[k], &region);  // the header: every file exists, if empty
    }
    const auto flush = [&](std::size_t k) {
      write_chunk(buffer[k], part[k], nullptr);
      total[k] += buffer[k].size();
      buffer[k] = Cloud{};
    };
    source([&](const Cloud& c) {
      for (std::size_t i = 0; i < c.size(); ++i) {
        const Vec3f& p = c.points[i];
        std::array<std::pair<int, int>, 3> range;  // block indices per axis whose span holds p
        bool any = true;
        for (int a = 0; a < 3 && any; ++a) {
          const auto& sp = span[std::size_t(a)];
          int lo = 0;
          while (lo < int(sp.size()) && !(p[a] <= sp[std::size_t(lo)].second)) ++lo;
          int hi = lo;
          while (hi < int(sp.size()) && p[a] >= sp[std::size_t(hi)].first) ++hi;
          range[std::size_t(a)] = {lo, hi};
          any = hi > lo;
        }
        if (!any) continue;
        for (int bk = range[2].first; bk < range[2].second; ++bk)
          for (int bj = range[1].first; bj < range[1].second; ++bj)
            for (int bi = range[0].first; bi < range[0].second; ++bi) {
              const int k = slot[std::size_t(grid.id(bi, bj, bk))];
              if (k < 0) continue;
              append(buffer[std::size_t(k)], c, i);
              if (buffer[std::size_t(k)].size() >= limit) flush(std::size_t(k));
            }
      }
    });
    for (std::size_t k = 0; k < ids.size(); ++k) {
      flush(k);
      write_trailer(part[k], total[k]);
    }
    for (std::size_t k = 0; k < ids.size(); ++k) std::filesystem::rename(part[k], path(ids[k]));
  } catch (...) {
    for (const std::string& f : part) {
      std::error_code ec;
      std::filesystem::remove(f, ec);
    }
    throw;
  }
}

Cloud read_bucket(const std::string& path, const Aabb* region) {
  const std::string bytes = read_file_bytes(path);
  const auto bad = [&](const std::string& why) { return FormatError(path + ": not a block's points (" + why + ")"); };
  if (bytes.size() < kBucketHeader || !header_matches(bytes.data(), nullptr)) throw bad("no header");
  if (region && !header_matches(bytes.data(), region)) throw bad("sorted for another block grid");
  Cloud out;
  std::size_t at = kBucketHeader;
  int kinds = -1;
  for (;;) {
    std::uint32_t n = 0;
    if (bytes.size() - at < 4) throw bad("cut short");
    std::memcpy(&n, bytes.data() + at, 4);
    at += 4;
    if (n == kBucketEnd) {
      std::uint64_t count = 0;
      if (bytes.size() - at != sizeof count) throw bad("cut short, or bytes after its end");
      std::memcpy(&count, bytes.data() + at, sizeof count);
      if (count != out.size()) throw bad("cut short");
      break;
    }
    if (n == 0 || bytes.size() - at < 1) throw bad("cut short");
    const int flags = std::uint8_t(bytes[at]);
    at += 1;
    if (flags > 3 || (kinds >= 0 && flags != kinds)) throw bad("mixed attributes");
    kinds = flags;
    const std::size_t need = std::size_t(n) * (12 + ((flags & 1) ? 12 : 0) + ((flags & 2) ? 3 : 0));
    if (bytes.size() - at < need) throw bad("cut short");
    const std::size_t base = out.size();
    out.points.resize(base + n);
    std::memcpy(out.points[base].data(), bytes.data() + at, std::size_t(n) * 12);
    at += std::size_t(n) * 12;
    if (flags & 1) {
      out.normals.resize(base + n);
      std::memcpy(out.normals[base].data(), bytes.data() + at, std::size_t(n) * 12);
      at += std::size_t(n) * 12;
    }
    if (flags & 2) {
      out.colours.resize(base + n);
      std::memcpy(&out.colours[base], bytes.data() + at, std::size_t(n) * 3);
      at += std::size_t(n) * 3;
    }
  }
  if (!all_finite(out.points)) throw bad("non-finite coordinates");
  return out;
}

// ------------------------------------------------------------------ memory

std::vector<std::size_t> estimate_block_points(const BlockSummary& s, const BlockGrid& g) {
  // Per axis, the blocks' intervals with the margin (as region()).
  std::array<std::vector<std::pair<double, double>>, 3> iv;
  for (std::size_t a = 0; a < 3; ++a)
    for (int b = 0; b < g.counts[a]; ++b)
      iv[a].emplace_back(float(g.lattice.origin[int(a)] + g.lattice.h * g.splits[a][std::size_t(b)] - g.margin),
                         float(g.lattice.origin[int(a)] + g.lattice.h * g.splits[a][std::size_t(b) + 1] + g.margin));
  std::vector<std::size_t> n(std::size_t(g.size()), 0);
  for (const Vec3f& p : s.far_field.points) {
    std::array<std::array<int, 2>, 3> r{};
    for (std::size_t a = 0; a < 3; ++a) {
      // The blocks whose interval holds the coordinate: a run of consecutive ones.
      int lo = 0;
      while (lo < g.counts[a] && iv[a][std::size_t(lo)].second < p[int(a)]) ++lo;
      int hi = lo;
      while (hi < g.counts[a] && iv[a][std::size_t(hi)].first <= p[int(a)]) ++hi;
      r[a] = {lo, hi};
    }
    for (int k = r[2][0]; k < r[2][1]; ++k)
      for (int j = r[1][0]; j < r[1][1]; ++j)
        for (int i = r[0][0]; i < r[0][1]; ++i) n[std::size_t(g.id(i, j, k))] += s.every;
  }
  return n;
}

double estimate_block_bytes(const BlockSummary& s, const BlockGrid& g) {
  const std::vector<std::size_t> n = estimate_block_points(s, g);
  const double most = double(std::min(n.empty() ? 0 : *std::max_element(n.begin(), n.end()), s.points));
  const double cells = s.sample_spacing > 0 ? std::pow(s.sample_spacing / g.lattice.h, 2) : 1;  // a point's
  return kBlockBaseBytes + kBlockBytesPerPoint * most + kBlockBytesPerExtraCell * most * std::max(0.0, cells - 1);
}

int resolve_block_count(const BlockSummary& s, int blocks, double max_bytes, int ranks) {
  if (blocks < 0) throw InvalidInput("blocks: auto (0) or a count");
  const int least = ranks > 1 ? std::min(4096, kAutoBlocksPerRank * ranks) : 1;
  if (!(max_bytes > 0)) {
    if (blocks == 0)
      return std::min<int>(4096, int(std::max<std::size_t>(std::size_t(least), (s.points + kAutoBlockPoints - 1) / kAutoBlockPoints)));
    return blocks;
  }
  const double cell = double((s.box.max - s.box.min).maxCoeff()) / s.resolution;
  const double margin = block_margin(s, cell);
  const auto need = [&](int n) { return estimate_block_bytes(s, plan_blocks(s.box, s.resolution, n, margin)); };
  const auto gb = [](double b) { return fmt("%.2f GB", b / 1e9); };
  if (kBlockBaseBytes > max_bytes)
    throw InvalidInput("--max-memory " + gb(max_bytes) + " is below what any block run needs (about " +
                       gb(kBlockBaseBytes) + " for the process and the cloud's summary)");
  // The fewest blocks that fit: counts grown by about a quarter at a time.
  int fits = 0;
  double at_most = 0;
  for (int n = 1; n <= 4096; n = std::max(n + 1, n * 5 / 4)) {
    const double b = need(n);
    if (b <= max_bytes) {
      fits = n;
      at_most = b;
      break;
    }
    at_most = b;
  }
  if (fits == 0)
    throw InvalidInput("the cloud does not fit --max-memory " + gb(max_bytes) + " per rank: even 4096 blocks need about " +
                       gb(at_most) + " (fewer points or a coarser --resolution would)");
  if (blocks > 1) {
    const double b = need(blocks);
    if (b > max_bytes)
      throw InvalidInput("--blocks " + std::to_string(blocks) + " needs about " + gb(b) + " per rank, over --max-memory " +
                         gb(max_bytes) + "; --blocks " + std::to_string(fits) + " or more fits");
    return blocks;
  }
  return std::max(fits, least);
}

std::vector<int> assign_blocks(const std::vector<int>& ids, const std::vector<std::size_t>& points, int ranks) {
  if (ranks < 1) throw InvalidInput("assign_blocks: at least one rank");
  std::vector<std::size_t> order(ids.size());
  std::iota(order.begin(), order.end(), std::size_t(0));
  const auto weight = [&](std::size_t t) {
    const int id = ids[t];
    return id >= 0 && std::size_t(id) < points.size() ? points[std::size_t(id)] : 0;
  };
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return weight(a) > weight(b); });
  std::vector<int> rank(ids.size(), 0);
  std::vector<std::size_t> load(std::size_t(ranks), 0);
  for (const std::size_t t : order) {
    const int r = int(std::min_element(load.begin(), load.end()) - load.begin());
    rank[t] = r;
    load[std::size_t(r)] += weight(t) + 1;  // + 1: empty blocks spread too
  }
  return rank;
}

// ------------------------------------------------------------------ one block

void block_dmc_seams(DmcOptions& o, const BlockGrid& grid, int id, const SeamTable& upper, SeamTable& lower,
                     std::unordered_map<std::uint64_t, DmcPoint>& given) {
  const LatticeWindow window = grid.window(id);
  for (std::size_t a = 0; a < 3; ++a) o.halo[a] = window.offset[a] > 0 ? kDmcHaloCells : 0;
  given.clear();
  for (const auto& [key, v] : upper)
    if (!is_seam_position_key(key)) {
      const auto x = upper.find(seam_position_key(key, 0)), y = upper.find(seam_position_key(key, 1)),
                 z = upper.find(seam_position_key(key, 2)), fl = upper.find(seam_flags_key(key));
      if (x != upper.end() && y != upper.end() && z != upper.end() && fl != upper.end())
        given.emplace(key, DmcPoint{Vec3d(x->second, y->second, z->second), v, std::uint8_t(fl->second)});
    }
  o.given = &given;
  const Vec3d origin = grid.lattice.origin;
  const double h = grid.lattice.h;
  o.report = [&lower, origin, h](int i, int j, int k, const DmcPoint& q) {
    const std::uint64_t key = lattice_point_key(i, j, k);
    const auto it = lower.find(key);
    if (it == lower.end()) return;  // not a point of this block's lower faces
    it->second = q.value;
    if ((q.pos - (origin + h * Vec3d(i, j, k))).norm() > 1e-9 * h || q.flags) {  // moved, or marked by a move
      for (int a = 0; a < 3; ++a) lower[seam_position_key(key, a)] = q.pos[a];
      lower[seam_flags_key(key)] = q.flags;
    }
  };
}

BlockMesh reconstruct_block(const Cloud& pts_in, const BlockGrid& grid, int id, const BlockSummary& s,
                            const SurfaceParams& p, const SeamTable& upper, SeamTable& lower) {
  const auto t0 = Clock::now();
  BlockMesh out;
  out.points = pts_in.size();
  const LatticeWindow window = grid.window(id);
  const double h = window.h;
  Cloud pts = pts_in;
  if (s.flip_normals)
    for (Vec3f& n : pts.normals) n = -n;
  const MpuParams defaults;
  if (pts.size() < std::size_t(defaults.n_min)) {
    // Too few points for a fit: nothing of the surface here; its lower faces read outside.
    Constant outside;
    outside.v = h;
    lower = lower_face_values(outside, grid, id, p.threads);
    out.seconds = seconds_since(t0);
    return out;
  }
  MpuParams mp;
  mp.epsilon0 = s.epsilon0;
  mp.threads = p.threads;
  if (s.hole == HoleMode::kKeep) mp.trust_factor = kKeepTrustFactor, mp.sparse_trust = true;
  // The whole cloud's frame and spacings: the block's octree is the whole fit's cut at
  // the block (the same cells, the same epsilon0 in input units, the same trust), so
  // beyond the data, where the closing blends MPU's extrapolation in, the blocks
  // extrapolate as the single run does.
  mp.frame = s.bounds;
  mp.mean_spacing = s.mean_spacing;
  mp.median_spacing = s.sample_spacing;
  // The fits take the points in Z order, as the single run's (reconstruct_surface).
  const std::vector<std::uint32_t> z_order = spatial_order(pts.points);
  const MpuSurface surface = fit_mpu(reordered(pts, z_order), mp);
  out.mpu = surface.diagnostics();
  const bool close = s.hole == HoleMode::kClose;
  std::unique_ptr<WindingClose> winding;
  Cloud winding_cloud;
  if (close && p.winding_close) {
    // Near field: the block's points; far field: the summary's points elsewhere.
    const Aabb region = grid.region(id);
    winding_cloud.points = pts.points;
    winding_cloud.normals = pts.normals;
    for (std::size_t i = 0; i < s.far_field.size(); ++i)
      if (!inside(region, s.far_field.points[i])) {
        winding_cloud.points.push_back(s.far_field.points[i]);
        winding_cloud.normals.push_back(s.far_field.normals[i]);
      }
    WindingCloseParams wp;
    wp.trust_distance = MpuParams().trust_factor * s.mean_spacing;
    wp.voxel = std::max(wp.trust_distance / 2, double(s.bounds.diagonal()) / 200);
    winding = std::make_unique<WindingClose>(surface, winding_cloud, wp);
  }
  const ImplicitFunction& closed = winding ? static_cast<const ImplicitFunction&>(*winding) : surface;
  std::unique_ptr<HalfSpaceClip> clip;
  if (close && p.table_up && p.table_up->norm() > 0 && s.table_height)
    clip = std::make_unique<HalfSpaceClip>(closed, p.table_up->normalized(), *s.table_height);
  const ImplicitFunction& f = clip ? static_cast<const ImplicitFunction&>(*clip) : closed;

  // The lattice values of the window's faces: its own lower faces (which the blocks
  // below take) and the upper faces from the blocks above.
  lower = lower_face_values(f, grid, id, p.threads);
  SeamTable faces = upper;
  faces.insert(lower.begin(), lower.end());
  const SeamValues field(f, grid.lattice, faces);

  MarchingCubesOptions mo;
  mo.untrusted = close ? UntrustedRegions::kClose : UntrustedRegions::kLeaveOpen;
  mo.threads = p.threads;
  mo.close_at_box = true;
  mo.window = window;
  mo.vertex_edges = &out.edges;
  for (const Vec3f& q : pts.points) mo.seeds.push_back(q);
  // The walk also starts next to every crossing on the window's faces, so a piece of
  // surface that enters the window without points of its own there is not missed.
  for (const auto& [key, v] : faces) {
    if (is_seam_position_key(key)) continue;
    const int ijk[3] = {int(key & 0xFFFFF), int(key >> 20 & 0xFFFFF), int(key >> 40 & 0xFFFFF)};
    for (int a = 0; a < 3; ++a) {
      int nb[3] = {ijk[0], ijk[1], ijk[2]};
      ++nb[a];
      const auto it = faces.find(lattice_point_key(nb[0], nb[1], nb[2]));
      if (it == faces.end() || ((v < 0) == (it->second < 0))) continue;
      const int b1 = (a + 1) % 3, b2 = (a + 2) % 3;
      for (int q = 0; q < 4; ++q) {
        int c[3] = {ijk[0], ijk[1], ijk[2]};
        c[b1] -= q & 1;
        c[b2] -= q >> 1;
        Vec3d centre;
        bool in = true;
        for (int t = 0; t < 3; ++t) {
          const int rel = c[t] - window.offset[std::size_t(t)];
          in = in && rel >= 0 && rel < window.cells[std::size_t(t)];
          centre[t] = window.origin[t] + h * (c[t] + 0.5);
        }
        if (in) mo.seeds.push_back(centre.cast<float>());
      }
    }
  }
  Mesh mesh;
  if (p.extractor == Extractor::kDmc) {
    DmcOptions dopt;
    static_cast<MarchingCubesOptions&>(dopt) = mo;
    std::unordered_map<std::uint64_t, DmcPoint> given;
    block_dmc_seams(dopt, grid, id, upper, lower, given);
    mesh = extract_dmc(field, Aabb{}, 1, dopt, &out.dmc);
  } else {
    MarchingCubesStats ms;
    mesh = extract_marching_cubes(field, Aabb{}, 1, mo, &ms);
    static_cast<MarchingCubesStats&>(out.dmc) = ms;
  }
  if (p.colour && s.colours && pts.has_colours() && !mesh.vertices.empty()) {
    if (p.colour_method == ColourMethod::kNearest) {
      transfer_colours(mesh, pts, {4, p.threads});
    } else {
      const ColourFunction cf = fit_colour(reordered(pts, z_order), colour_params(p));
      out.colour = cf.diagnostics();
      out.colour_nearest_vertices = colour_mesh(mesh, cf, surface, pts, p.threads);
      if (p.colour_edges) {
        // As the single run splits them, but never an edge on a shared face (both its
        // ends seam vertices): the block beyond sees the same edge and must not
        // differ. The new vertices lie on no lattice edge.
        ColourEdgeParams ep;
        ep.threads = p.threads;
        ep.keep_edge = [&](int a, int b) {
          return grid.on_seam(out.edges[std::size_t(a)]) && grid.on_seam(out.edges[std::size_t(b)]);
        };
        out.colour_edges_split = sharpen_colour_edges(mesh, cf, ep).split_edges;
        out.edges.resize(mesh.vertices.size(), kNoLatticeEdge);
      }
      if (p.boundary_flags) {
        out.boundary.resize(mesh.vertices.size());
        for (std::size_t v = 0; v < mesh.vertices.size(); ++v)
          out.boundary[v] = cf.dominant_type(mesh.vertices[v].cast<double>()) == ColourCellType::kB;
      }
    }
  }
  if (!close && s.mean_spacing > 0) {
    out.far.resize(mesh.vertices.size());
    const double bound = kRimTrimFactor * s.mean_spacing;
    for (std::size_t v = 0; v < mesh.vertices.size(); ++v)
      out.far[v] = !surface.near_points(mesh.vertices[v].cast<double>(), bound);
  }
  out.mesh = std::move(mesh);
  out.seconds = seconds_since(t0);
  return out;
}

// ------------------------------------------------------------------ stitching

Mesh stitch_blocks(std::vector<BlockMesh>& pieces, const BlockGrid& grid, std::vector<char>* far,
                   std::vector<std::uint8_t>* boundary) {
  Mesh out;
  bool normals = true, colours = true, any = false;
  std::size_t nv = 0, nf = 0;
  for (const BlockMesh& b : pieces) {
    if (b.mesh.vertices.empty()) continue;
    if (b.edges.size() != b.mesh.vertices.size()) throw InvalidInput("stitch_blocks: a block's vertices have no lattice edges");
    any = true;
    normals = normals && b.mesh.has_normals();
    colours = colours && b.mesh.has_colours();
    nv += b.mesh.vertices.size();
    nf += b.mesh.faces.size();
  }
  if (!any) return out;
  out.vertices.reserve(nv);
  out.faces.reserve(nf);
  if (normals) out.normals.reserve(nv);
  if (colours) out.colours.reserve(nv);
  if (far) far->clear();
  bool flags = boundary != nullptr;
  for (const BlockMesh& b : pieces)
    if (!b.mesh.vertices.empty()) flags = flags && b.boundary.size() == b.mesh.vertices.size();
  if (boundary) boundary->clear();
  std::unordered_map<std::uint64_t, int> seam;
  for (BlockMesh& b : pieces) {
    if (b.mesh.vertices.empty()) continue;
    std::vector<int> id(b.mesh.vertices.size());
    for (std::size_t v = 0; v < id.size(); ++v) {
      if (grid.on_seam(b.edges[v])) {
        const auto [it, fresh] = seam.emplace(b.edges[v], int(out.vertices.size()));
        if (!fresh) {
          id[v] = it->second;
          continue;
        }
      }
      id[v] = int(out.vertices.size());
      out.vertices.push_back(b.mesh.vertices[v]);
      if (normals) out.normals.push_back(b.mesh.normals[v]);
      if (colours) out.colours.push_back(b.mesh.colours[v]);
      if (far) far->push_back(b.far.empty() ? 0 : b.far[v]);
      if (flags) boundary->push_back(b.boundary[v]);
    }
    for (const Face& fc : b.mesh.faces) out.faces.push_back({id[std::size_t(fc[0])], id[std::size_t(fc[1])], id[std::size_t(fc[2])]});
    b.mesh = Mesh{};
    b.edges.clear();
    b.far.clear();
    b.boundary.clear();
  }
  return out;
}

namespace {

// The summary's decisions in a result, before the pieces' figures.
SurfaceResult block_result(const BlockGrid& grid, const BlockSummary& s) {
  SurfaceResult out;
  out.hole = s.hole;
  out.enclosure = s.enclosure;
  out.normals_flipped = s.flip_normals;
  out.epsilon0 = s.epsilon0;
  out.resolution = s.resolution;
  out.resolution_auto = s.resolution_auto;
  out.table_height = s.table_height;
  out.extraction.cell_size = grid.lattice.h;
  out.mpu.mean_spacing = s.mean_spacing;
  out.mpu.sample_spacing = s.sample_spacing;
  out.mpu.input_points = s.points;
  return out;
}

void add_piece_figures(SurfaceResult& out, const BlockMesh& b) {
  out.colour_nearest_vertices += b.colour_nearest_vertices;
  out.colour_edges_split += b.colour_edges_split;
  if (b.colour && b.colour->input_points > 0) {
    if (!out.colour) out.colour = ColourDiagnostics{};
    ColourDiagnostics& c = *out.colour;
    const double n = double(c.input_points), m = double(b.colour->input_points);
    c.e_col = (c.e_col * n + b.colour->e_col * m) / (n + m);
    c.e_col_points += b.colour->e_col_points;
    c.input_points += b.colour->input_points;
    c.leaves += b.colour->leaves;
    c.cells += b.colour->cells;
    for (int t = 0; t < 2; ++t) c.leaves_by_type[std::size_t(t)] += b.colour->leaves_by_type[std::size_t(t)];
  }
  out.extraction.cells_visited += b.dmc.cells_visited;
  out.extraction.surface_cells += b.dmc.surface_cells;
  out.extraction.evaluations += b.dmc.evaluations;
  out.extraction.dropped_faces += b.dmc.dropped_faces;
  out.mpu.leaves += b.mpu.leaves;
}

}  // namespace

SurfaceResult assemble_blocks(std::vector<BlockMesh>& pieces, const BlockGrid& grid, const BlockSummary& s,
                              const SurfaceParams& p, BlockRunStats* stats) {
  const auto note = [&](const std::string& line) {
    if (p.note) p.note(line);
  };
  SurfaceResult out = block_result(grid, s);
  std::size_t before = 0;
  for (const BlockMesh& b : pieces) {
    before += b.mesh.vertices.size();
    add_piece_figures(out, b);
  }
  std::vector<char> far;
  std::vector<std::uint8_t> boundary;
  Mesh mesh = stitch_blocks(pieces, grid, &far, p.boundary_flags ? &boundary : nullptr);
  const std::size_t joined = before - mesh.vertices.size();
  if (stats) stats->seam_vertices_joined = joined;
  if (mesh.faces.empty()) throw InvalidInput("the reconstructed surface is empty");
  out.coloured = p.colour && s.colours && mesh.has_colours();
  note("stitched " + std::to_string(grid.size()) + " blocks: " + std::to_string(mesh.vertices.size()) + " vertices, " +
       std::to_string(mesh.faces.size()) + " faces (" + std::to_string(joined) + " seam vertices joined)");
  const bool flagged = !boundary.empty() && boundary.size() == mesh.vertices.size();
  if (s.hole == HoleMode::kKeep && far.size() == mesh.vertices.size()) {
    std::vector<std::uint64_t> keys(boundary.begin(), boundary.end());  // the flags follow the vertices kept
    out.rim_faces = trim_open_rims(mesh, far, 16, nullptr, flagged ? &keys : nullptr);
    if (flagged) boundary.assign(keys.begin(), keys.end());
  }
  if (out.rim_faces > 0) note("open rims brought back to the data (" + std::to_string(out.rim_faces) + " faces)");
  out.pieces = remove_small_components(mesh, p.min_component, flagged ? &boundary : nullptr);
  if (flagged) out.colour_boundary = std::move(boundary);
  if (out.pieces.removed_components > 0)
    note("removed " + std::to_string(out.pieces.removed_components) + " small pieces (" +
         std::to_string(out.pieces.removed_faces) + " faces)");
  if (stats) {
    stats->vertices = mesh.vertices.size();
    stats->faces = mesh.faces.size();
  }
  out.mesh = std::move(mesh);
  return out;
}

namespace {

// A piece as the streamed writer takes it: rims trimmed block by block with holes kept
// (the edges on shared faces pinned), its vertices' pieces of surface (connected
// through its own faces) numbered in the order of their first vertex, with each
// piece's area and faces.
struct PreparedPiece {
  BlockMesh b;
  std::vector<int> part;  ///< per vertex: its piece of surface (0..parts-1)
  std::vector<double> area;
  std::vector<std::size_t> faces;
  std::size_t rim_faces = 0;
};

PreparedPiece prepare_piece(BlockMesh b, const BlockGrid& grid, bool keep) {
  PreparedPiece pp;
  const std::size_t nv = b.mesh.vertices.size();
  if (b.edges.size() != nv) throw InvalidInput("write_blocks_ply: a block's vertices have no lattice edges");
  if (keep && b.far.size() == nv && !b.mesh.faces.empty()) {
    std::vector<char> pinned(nv);
    for (std::size_t v = 0; v < nv; ++v) pinned[v] = grid.on_seam(b.edges[v]) ? 1 : 0;
    pp.rim_faces = trim_open_rims(b.mesh, b.far, 16, &pinned, &b.edges);
  }
  b.far.clear();
  UnionFind uf(b.mesh.vertices.size());
  for (const Face& f : b.mesh.faces) {
    uf.unite(f[0], f[1]);
    uf.unite(f[0], f[2]);
  }
  pp.part.assign(b.mesh.vertices.size(), -1);
  std::vector<int> of_root(b.mesh.vertices.size(), -1);
  for (std::size_t v = 0; v < pp.part.size(); ++v) {
    int& r = of_root[std::size_t(uf.find(int(v)))];
    if (r < 0) {
      r = int(pp.area.size());
      pp.area.push_back(0);
      pp.faces.push_back(0);
    }
    pp.part[v] = r;
  }
  for (const Face& f : b.mesh.faces) {
    const Vec3d a = b.mesh.vertices[std::size_t(f[0])].cast<double>();
    const double A = 0.5 * (b.mesh.vertices[std::size_t(f[1])].cast<double>() - a)
                               .cross(b.mesh.vertices[std::size_t(f[2])].cast<double>() - a)
                               .norm();
    const int q = pp.part[std::size_t(f[0])];
    pp.area[std::size_t(q)] += std::isfinite(A) ? A : 0.0;
    ++pp.faces[std::size_t(q)];
  }
  pp.b = std::move(b);
  return pp;
}

// Appends `bytes` to `out` and clears them, or throws IoError naming `what`.
void flush_to(std::ostream& out, std::string& bytes, const std::string& what) {
  out.write(bytes.data(), std::streamsize(bytes.size()));
  if (!out) throw IoError(what + ": write failed (disk full?)");
  bytes.clear();
}

}  // namespace

SurfaceResult write_blocks_ply(const std::function<BlockMesh(int)>& load, const BlockGrid& grid,
                               const BlockSummary& s, const SurfaceParams& p, const std::string& path,
                               const std::string& scratch, BlockRunStats* stats) {
  const auto note = [&](const std::string& line) {
    if (p.note) p.note(line);
  };
  const bool keep = s.hole == HoleMode::kKeep;
  SurfaceResult out = block_result(grid, s);

  // Pass 1: the pieces of surface, joined across the seams; their areas decide which
  // are small (as remove_small_components on the stitched mesh).
  struct SeamVertex {
    int slot;
    std::int64_t index = -1;  ///< its vertex in the written mesh (pass 2)
  };
  std::unordered_map<std::uint64_t, SeamVertex> seam;
  UnionFind slots;
  std::vector<double> area;
  std::vector<std::size_t> faces_of, fresh_of;  // per slot: faces, vertices not joined to an earlier block's
  std::vector<int> first_slot(std::size_t(grid.size()) + 1, 0);
  bool normals = true, colours = true, any = false;
  std::size_t joined = 0;
  for (int id = 0; id < grid.size(); ++id) {
    PreparedPiece pp = prepare_piece(load(id), grid, keep);
    add_piece_figures(out, pp.b);
    out.rim_faces += pp.rim_faces;
    first_slot[std::size_t(id)] = int(area.size());
    for (std::size_t q = 0; q < pp.area.size(); ++q) {
      slots.add();
      area.push_back(pp.area[q]);
      faces_of.push_back(pp.faces[q]);
      fresh_of.push_back(0);
    }
    const Mesh& m = pp.b.mesh;
    if (!m.vertices.empty()) {
      any = true;
      normals = normals && m.has_normals();
      colours = colours && m.has_colours();
    }
    for (std::size_t v = 0; v < m.vertices.size(); ++v) {
      const int slot = first_slot[std::size_t(id)] + pp.part[v];
      if (grid.on_seam(pp.b.edges[v])) {
        const auto [it, fresh] = seam.emplace(pp.b.edges[v], SeamVertex{slot});
        if (!fresh) {
          slots.unite(slot, it->second.slot);
          ++joined;
          continue;
        }
      }
      ++fresh_of[std::size_t(slot)];
    }
  }
  first_slot[std::size_t(grid.size())] = int(area.size());
  if (!any) throw InvalidInput("the reconstructed surface is empty");
  if (stats) stats->seam_vertices_joined = joined;
  // Per joined piece of surface (root slot): area, whether it has faces, kept.
  const std::size_t ns = area.size();
  std::vector<double> root_area(ns, 0);
  std::vector<std::size_t> root_faces(ns, 0);
  for (std::size_t q = 0; q < ns; ++q) {
    const std::size_t r = std::size_t(slots.find(int(q)));
    root_area[r] += area[q];
    root_faces[r] += faces_of[q];
  }
  ComponentFilterStats& cs = out.pieces;
  for (std::size_t r = 0; r < ns; ++r)
    if (slots.find(int(r)) == int(r) && root_faces[r] > 0) {
      ++cs.components;
      cs.largest_area = std::max(cs.largest_area, root_area[r]);
    }
  const double min_area = p.min_component * cs.largest_area;
  std::vector<char> keep_root(ns, 1);
  for (std::size_t r = 0; r < ns; ++r)
    if (slots.find(int(r)) == int(r) && root_faces[r] > 0 && root_area[r] < min_area) {
      keep_root[r] = 0;
      ++cs.removed_components;
      cs.removed_faces += root_faces[r];
    }
  // A vertex of no face stays only when nothing was removed (remove_small_components
  // drops unused vertices when it drops anything).
  if (cs.removed_components > 0)
    for (std::size_t r = 0; r < ns; ++r)
      if (slots.find(int(r)) == int(r) && root_faces[r] == 0) keep_root[r] = 0;
  const auto kept = [&](int slot) { return keep_root[std::size_t(slots.find(slot))] != 0; };
  std::size_t nv = 0, nf = 0;
  for (std::size_t q = 0; q < ns; ++q)
    if (kept(int(q))) {
      nv += fresh_of[q];
      nf += faces_of[q];
    }
  if (nf == 0) throw InvalidInput("the reconstructed surface is empty");
  if (nv > std::size_t(std::numeric_limits<std::int32_t>::max()))
    throw InvalidInput("the mesh has " + std::to_string(nv) + " vertices, more than a PLY's int indices hold");
  out.coloured = p.colour && s.colours && colours;
  note("stitching " + std::to_string(grid.size()) + " blocks into " + path + ": " + std::to_string(nv) +
       " vertices, " + std::to_string(nf) + " faces (" + std::to_string(joined) + " seam vertices joined)");
  if (out.rim_faces > 0) note("open rims brought back to the data (" + std::to_string(out.rim_faces) + " faces)");
  if (cs.removed_components > 0)
    note("removed " + std::to_string(cs.removed_components) + " small pieces (" + std::to_string(cs.removed_faces) +
         " faces)");

  // Pass 2: the vertices straight into the file, the faces into the scratch file, which
  // is appended after the last vertex.
  write_file_atomic(path, [&](std::ostream& os) {
    std::string buf = ply_header(nv, normals, colours, nf, true);
    std::ofstream fs(scratch, std::ios::binary | std::ios::trunc);
    if (!fs) throw IoError(scratch + ": cannot write");
    std::string fbuf;
    std::int64_t next = 0;
    std::vector<std::int32_t> index;
    for (int id = 0; id < grid.size(); ++id) {
      PreparedPiece pp = prepare_piece(load(id), grid, keep);
      const Mesh& m = pp.b.mesh;
      index.assign(m.vertices.size(), -1);
      for (std::size_t v = 0; v < m.vertices.size(); ++v) {
        const int slot = first_slot[std::size_t(id)] + pp.part[v];
        if (!kept(slot)) continue;
        std::int64_t* at = nullptr;
        if (grid.on_seam(pp.b.edges[v])) {
          at = &seam.at(pp.b.edges[v]).index;
          if (*at >= 0) {
            index[v] = std::int32_t(*at);
            continue;
          }
        }
        if (at) *at = next;
        index[v] = std::int32_t(next++);
        put_ply_vertex(buf, m.vertices[v], normals ? &m.normals[v] : nullptr, colours ? &m.colours[v] : nullptr);
      }
      for (const Face& f : m.faces) {
        if (!kept(first_slot[std::size_t(id)] + pp.part[std::size_t(f[0])])) continue;
        put_ply_face(fbuf, Face(index[std::size_t(f[0])], index[std::size_t(f[1])], index[std::size_t(f[2])]));
      }
      flush_to(os, buf, path);
      flush_to(fs, fbuf, scratch);
    }
    if (std::size_t(next) != nv) throw InvalidInput("write_blocks_ply: the blocks changed between the passes");
    fs.close();
    if (!fs) throw IoError(scratch + ": write failed (disk full?)");
    std::ifstream in(scratch, std::ios::binary);
    std::vector<char> chunk(std::size_t(1) << 22);
    while (in) {
      in.read(chunk.data(), std::streamsize(chunk.size()));
      os.write(chunk.data(), in.gcount());
      if (!os) throw IoError(path + ": write failed (disk full?)");
    }
  });
  std::error_code ec;
  std::filesystem::remove(scratch, ec);
  if (stats) {
    stats->vertices = nv;
    stats->faces = nf;
  }
  return out;
}

// ------------------------------------------------------------------ files

CloudSource file_source(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  if (ext == ".ply")
    return [path](const std::function<void(const Cloud&)>& chunk) { stream_ply_points(path, 65536, chunk); };
  auto cloud = std::make_shared<Cloud>(read_cloud(path));
  return [cloud](const std::function<void(const Cloud&)>& chunk) { chunk(*cloud); };
}

namespace {

constexpr std::uint32_t kMagic = 0x4B4C4253;  // "SBLK"
// File kinds after the magic: 1 summary, 3 seam table, 7 piece (2: a piece before
// 2026-12-05; 4 and 5 briefly, without the colour function's figures or flags; 6
// without the points e_col was taken over).
constexpr std::uint32_t kPieceFormat = 7;

class Writer {
 public:
  template <class T>
  void put(const T& v) {
    out.append(reinterpret_cast<const char*>(&v), sizeof(T));
  }
  template <class T>
  void put_vector(const std::vector<T>& v) {
    put(std::uint64_t(v.size()));
    out.append(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
  }
  std::string out;
};

class Reader {
 public:
  Reader(const std::string& bytes, const std::string& what) : b_(bytes), what_(what) {}
  template <class T>
  T get() {
    need(sizeof(T));
    T v;
    std::memcpy(static_cast<void*>(&v), b_.data() + at_, sizeof(T));
    at_ += sizeof(T);
    return v;
  }
  template <class T>
  std::vector<T> get_vector() {
    const std::uint64_t n = get<std::uint64_t>();
    if (n > (b_.size() - at_) / sizeof(T)) fail();
    std::vector<T> v(n);
    std::memcpy(static_cast<void*>(v.data()), b_.data() + at_, n * sizeof(T));
    at_ += n * sizeof(T);
    return v;
  }
  void header(std::uint32_t kind) {
    if (get<std::uint32_t>() != kMagic || get<std::uint32_t>() != kind) fail();
  }
  void end() const {
    if (at_ != b_.size()) fail();
  }
  [[noreturn]] void fail() const {
    throw FormatError(what_ + ": not a block file of this station version (or truncated); run again without --resume");
  }

 private:
  void need(std::size_t n) const {
    if (b_.size() - at_ < n) fail();
  }
  const std::string& b_;
  std::string what_;
  std::size_t at_ = 0;
};

}  // namespace

std::string to_bytes(const BlockSummary& s) {
  Writer w;
  w.put(kMagic);
  w.put(std::uint32_t(1));
  w.put_vector(s.far_field.points);
  w.put_vector(s.far_field.normals);
  w.put(std::uint64_t(s.every));
  w.put(std::uint64_t(s.points));
  w.put(s.bounds);
  w.put(std::uint8_t(s.colours));
  w.put(s.epsilon0);
  w.put(int(s.hole));
  w.put(std::uint8_t(bool(s.enclosure)));
  w.put(s.enclosure.value_or(0.0));
  w.put(std::uint8_t(s.flip_normals));
  w.put(s.mean_spacing);
  w.put(s.sample_spacing);
  w.put(s.resolution);
  w.put(std::uint8_t(s.resolution_auto));
  w.put(std::uint8_t(bool(s.table_height)));
  w.put(s.table_height.value_or(0.0));
  w.put(s.box);
  return w.out;
}

BlockSummary summary_from_bytes(const std::string& bytes, const std::string& what) {
  Reader r(bytes, what);
  r.header(1);
  BlockSummary s;
  s.far_field.points = r.get_vector<Vec3f>();
  s.far_field.normals = r.get_vector<Vec3f>();
  s.every = std::size_t(r.get<std::uint64_t>());
  s.points = std::size_t(r.get<std::uint64_t>());
  s.bounds = r.get<Aabb>();
  s.colours = r.get<std::uint8_t>();
  s.epsilon0 = r.get<double>();
  s.hole = HoleMode(r.get<int>());
  const bool enclosure = r.get<std::uint8_t>();
  const double e = r.get<double>();
  if (enclosure) s.enclosure = e;
  s.flip_normals = r.get<std::uint8_t>();
  s.mean_spacing = r.get<double>();
  s.sample_spacing = r.get<double>();
  s.resolution = r.get<int>();
  s.resolution_auto = r.get<std::uint8_t>();
  const bool table = r.get<std::uint8_t>();
  const double t = r.get<double>();
  if (table) s.table_height = t;
  s.box = r.get<Aabb>();
  r.end();
  if (s.far_field.normals.size() != s.far_field.points.size()) r.fail();
  return s;
}

std::string to_bytes(const BlockMesh& b) {
  Writer w;
  w.put(kMagic);
  w.put(std::uint32_t(kPieceFormat));
  w.put_vector(b.mesh.vertices);
  w.put_vector(b.mesh.normals);
  w.put_vector(b.mesh.colours);
  w.put_vector(b.mesh.faces);
  w.put_vector(b.edges);
  w.put_vector(b.far);
  w.put_vector(b.boundary);
  w.put(std::uint64_t(b.points));
  w.put(std::uint64_t(b.colour_nearest_vertices));
  w.put(std::uint64_t(b.mpu.leaves));
  w.put(std::uint64_t(b.dmc.cells_visited));
  w.put(std::uint64_t(b.dmc.surface_cells));
  w.put(std::uint64_t(b.dmc.evaluations));
  w.put(std::uint64_t(b.dmc.dropped_faces));
  w.put(std::uint64_t(b.colour_edges_split));
  w.put(std::uint8_t(b.colour.has_value()));
  if (b.colour) {
    w.put(std::uint64_t(b.colour->input_points));
    w.put(std::uint64_t(b.colour->cells));
    w.put(std::uint64_t(b.colour->leaves));
    w.put(std::uint64_t(b.colour->leaves_by_type[0]));
    w.put(std::uint64_t(b.colour->leaves_by_type[1]));
    w.put(b.colour->e_col);
    w.put(std::uint64_t(b.colour->e_col_points));
  }
  w.put(b.seconds);
  return w.out;
}

BlockMesh piece_from_bytes(const std::string& bytes, const std::string& what) {
  Reader r(bytes, what);
  r.header(kPieceFormat);
  BlockMesh b;
  b.mesh.vertices = r.get_vector<Vec3f>();
  b.mesh.normals = r.get_vector<Vec3f>();
  b.mesh.colours = r.get_vector<Rgb>();
  b.mesh.faces = r.get_vector<Face>();
  b.edges = r.get_vector<std::uint64_t>();
  b.far = r.get_vector<char>();
  b.boundary = r.get_vector<std::uint8_t>();
  b.points = std::size_t(r.get<std::uint64_t>());
  b.colour_nearest_vertices = std::size_t(r.get<std::uint64_t>());
  b.mpu.leaves = std::size_t(r.get<std::uint64_t>());
  b.dmc.cells_visited = std::size_t(r.get<std::uint64_t>());
  b.dmc.surface_cells = std::size_t(r.get<std::uint64_t>());
  b.dmc.evaluations = std::size_t(r.get<std::uint64_t>());
  b.dmc.dropped_faces = std::size_t(r.get<std::uint64_t>());
  b.colour_edges_split = std::size_t(r.get<std::uint64_t>());
  if (r.get<std::uint8_t>()) {
    ColourDiagnostics c;
    c.input_points = std::size_t(r.get<std::uint64_t>());
    c.cells = std::size_t(r.get<std::uint64_t>());
    c.leaves = std::size_t(r.get<std::uint64_t>());
    c.leaves_by_type[0] = std::size_t(r.get<std::uint64_t>());
    c.leaves_by_type[1] = std::size_t(r.get<std::uint64_t>());
    c.e_col = r.get<double>();
    c.e_col_points = std::size_t(r.get<std::uint64_t>());
    b.colour = c;
  }
  b.seconds = r.get<double>();
  r.end();
  const std::size_t nv = b.mesh.vertices.size();
  if ((!b.mesh.normals.empty() && b.mesh.normals.size() != nv) || (!b.mesh.colours.empty() && b.mesh.colours.size() != nv) ||
      b.edges.size() != nv || (!b.far.empty() && b.far.size() != nv) || (!b.boundary.empty() && b.boundary.size() != nv))
    r.fail();
  for (const Face& f : b.mesh.faces)
    for (int t = 0; t < 3; ++t)
      if (f[t] < 0 || std::size_t(f[t]) >= nv) r.fail();
  return b;
}

std::string to_bytes(const SeamTable& table) {
  std::vector<std::pair<std::uint64_t, double>> entries(table.begin(), table.end());
  std::sort(entries.begin(), entries.end());
  Writer w;
  w.put(kMagic);
  w.put(std::uint32_t(3));
  w.put_vector(entries);
  return w.out;
}

SeamTable table_from_bytes(const std::string& bytes, const std::string& what) {
  Reader r(bytes, what);
  r.header(3);
  const auto entries = r.get_vector<std::pair<std::uint64_t, double>>();
  r.end();
  return SeamTable(entries.begin(), entries.end());
}

// ------------------------------------------------------------------ in sequence

BlockPieces reconstruct_block_pieces(const CloudSource& source, const SurfaceParams& p, int blocks,
                                     BlockRunStats* stats, double max_bytes) {
  const auto note = [&](const std::string& line) {
    if (p.note) p.note(line);
  };
  if (blocks < 0) throw InvalidInput("blocks: auto (0) or a count");
  BlockPieces out;
  out.summary = summarise_cloud(source, p);
  const BlockSummary& s = out.summary;
  blocks = resolve_block_count(s, blocks, max_bytes);
  const double cell = double((s.box.max - s.box.min).maxCoeff()) / s.resolution;
  out.grid = plan_blocks(s.box, s.resolution, blocks, block_margin(s, cell));
  const BlockGrid& grid = out.grid;
  note(std::to_string(s.points) + " points in " + std::to_string(grid.size()) + " blocks (" +
       std::to_string(grid.counts[0]) + " x " + std::to_string(grid.counts[1]) + " x " + std::to_string(grid.counts[2]) +
       ") of one lattice of " + std::to_string(s.resolution) + " cells (cell " + fmt("%.3g", cell) + ", margin " +
       fmt("%.3g", grid.margin) + "); " + (s.hole == HoleMode::kClose ? "closing" : "keeping") + " the unseen parts");
  std::map<int, SeamTable> published;
  std::vector<BlockMesh>& pieces = out.pieces;
  pieces.resize(std::size_t(grid.size()));
  BlockRunStats st;
  st.blocks = grid.size();
  st.counts = grid.counts;
  int done = 0;
  for (const int id : block_order(grid)) {
    const auto c = grid.coords(id);
    SeamTable upper;
    for (int q = 1; q < 8; ++q) {
      const int ni = c[0] + (q & 1), nj = c[1] + (q >> 1 & 1), nk = c[2] + (q >> 2 & 1);
      if (ni >= grid.counts[0] || nj >= grid.counts[1] || nk >= grid.counts[2]) continue;
      const auto it = published.find(grid.id(ni, nj, nk));
      if (it != published.end()) upper.insert(it->second.begin(), it->second.end());
    }
    const Cloud pts = block_points(source, grid, id);
    st.max_block_points = std::max(st.max_block_points, pts.size());
    SeamTable lower;
    pieces[std::size_t(id)] = reconstruct_block(pts, grid, id, s, p, upper, lower);
    published[id] = std::move(lower);
    ++done;
    note("block " + std::to_string(done) + "/" + std::to_string(grid.size()) + " (" + std::to_string(c[0]) + ", " +
         std::to_string(c[1]) + ", " + std::to_string(c[2]) + "): " + std::to_string(pts.size()) + " points, " +
         std::to_string(pieces[std::size_t(id)].mesh.faces.size()) + " faces, " +
         fmt("%.2f s", pieces[std::size_t(id)].seconds));
  }
  if (stats) *stats = st;
  return out;
}

SurfaceResult reconstruct_surface_blocks(const CloudSource& source, const SurfaceParams& p, int blocks,
                                         BlockRunStats* stats, double max_bytes) {
  const auto t0 = Clock::now();
  BlockRunStats st;
  BlockPieces b = reconstruct_block_pieces(source, p, blocks, &st, max_bytes);
  SurfaceResult out = assemble_blocks(b.pieces, b.grid, b.summary, p, &st);
  out.seconds.total = seconds_since(t0);
  if (stats) *stats = st;
  return out;
}

}  // namespace station
