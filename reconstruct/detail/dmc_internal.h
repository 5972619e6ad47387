// The Dmc class and its lattice, shared by the files of its phases (dmc.cpp: set-up,
// traversal and evaluation; dmc_barycentre.cpp: step 1; dmc_features.cpp: crossings and
// step 2; dmc_mesh.cpp: step 3). Internal to reconstruct/: include only from there.
#pragma once


#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <array>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <stdexcept>
#include <unordered_map>
#include <unordered_set>

#include "core/error.h"
#include "core/threads.h"
#include "reconstruct/detail/lattice_storage.h"
#include "reconstruct/detail/mc_tables.h"
#include "reconstruct/mpu.h"

#include "reconstruct/dmc.h"

namespace station::detail::dmc {


// Lattice point / cell key: 21 bits per axis (as in marching_cubes.cpp).
using Key = std::uint64_t;
inline Key key(std::int64_t i, std::int64_t j, std::int64_t k) { return Key(i) | Key(j) << 21 | Key(k) << 42; }
inline int ki(Key k) { return int(k & 0x1FFFFF); }
inline int kj(Key k) { return int(k >> 21 & 0x1FFFFF); }
inline int kk(Key k) { return int(k >> 42 & 0x1FFFFF); }
// std::lround (halves away from zero) without the library call for lattice
// coordinates in [0, 2^31): truncation is the floor there and y - floor(y) is exact.
inline std::int64_t round_coordinate(double y) {
  if (!(y >= 0 && y < 2147483648.0)) return std::lround(y);
  const std::int64_t t = std::int64_t(y);
  return t + (y - double(t) >= 0.5 ? 1 : 0);
}
inline Key corner_key(Key cell, int q) { return key(ki(cell) + (q & 1), kj(cell) + (q >> 1 & 1), kk(cell) + (q >> 2 & 1)); }

// Lattice points grouped in blocks of 4^3: a small hash from block to block index.
class BlockIndex {
 public:
  static Key block_of(Key k) { return k & ~(Key(3) | Key(3) << 21 | Key(3) << 42); }
  static int local(Key k) { return int((k & 3) | (k >> 21 & 3) << 2 | (k >> 42 & 3) << 4); }
  std::uint32_t find(Key block) const {
    const std::int32_t b = table_.find(block);
    return b == detail::BlockTable::kAbsent ? kNone : std::uint32_t(b);
  }
  /// Index of the block (new blocks get the next index).
  std::uint32_t get(Key block, bool& added) {
    const std::int32_t b = table_.find_or_insert(block, std::int32_t(keys_.size()), added);
    if (added) keys_.push_back(block);
    return std::uint32_t(b);
  }
  const std::vector<Key>& keys() const { return keys_; }
  static constexpr std::uint32_t kNone = 0xFFFFFFFFu;

 private:
  detail::BlockTable table_{1 << 10};
  std::vector<Key> keys_;
};

// Set of lattice keys (cells), one bit per key in blocks of 4^3 (the seed cells).
class KeySet {
 public:
  KeySet() = default;
  template <class It>
  KeySet(It first, It last) {
    for (; first != last; ++first) insert(*first);
  }
  std::size_t count(Key k) const {
    const std::uint32_t b = index_.find(BlockIndex::block_of(k));
    return b != BlockIndex::kNone && (bits_[b] >> BlockIndex::local(k) & 1);
  }
  /// True when k was not in the set.
  bool insert(Key k) {
    bool added = false;
    const std::uint32_t b = index_.get(BlockIndex::block_of(k), added);
    if (added) bits_.push_back(0);
    const std::uint64_t m = std::uint64_t(1) << BlockIndex::local(k);
    if (bits_[b] & m) return false;
    bits_[b] |= m;
    return true;
  }

 private:
  BlockIndex index_;
  std::vector<std::uint64_t> bits_;
};

using detail::Chunked;

// kPassedPart / kPassedGap: the point has passed the thin part's (gap's) flood on
// (barycentre_step; once each).
enum : std::uint8_t {
  kFixed = 1, kSearched = 2, kBary = 4, kGap = 8, kCorner = 16, kEdge = 32, kPassedPart = 64, kPassedGap = 128
};

struct Node {
  Vec3d pos;
  double val;  // f(pos) - iso; NaN stored as outside
  std::uint8_t flags;
};

struct Crossing {
  int evals = 0;
  bool stale = false;  // an end moved after it was computed
  Vec3d pos = Vec3d::Zero();
  Vec3d normal = Vec3d::Zero();  // unit, or zero where the gradient is not usable
  int vid = -1;  // mesh vertex (build_mesh)
  std::int32_t refined = -1;  // the same crossing refined to round-off (feature_step), or -1
};

// DMC's lattice near the surface (docs/dmc.md, "Sparse storage"): blocks of 4^3 lattice
// points (and of the 4^3 cells whose lowest corner they are) behind a block hash. A
// block holds the index of each entered point's node, bit masks of the entered points,
// the crossed cells and a scratch set, the crossings on the three lattice edges from
// each point (slots made when the block gets its first), and links to its 26
// neighbouring blocks, cached
// as they are looked up (a block, once there, stays; a missing one is looked up again),
// so a cell's corners and a point's neighbours are found without hashing.
class Lattice {
 public:
  static constexpr std::int32_t kNone = -1, kUnknown = -2;
  struct Block {
    int bi, bj, bk;
    std::uint64_t present;  // points with a node
    std::uint64_t surface;  // crossed cells
    std::uint64_t mark;     // scratch set of points or cells (cleared after use)
    std::uint64_t mark2;    // a second scratch set
    std::int32_t nb[27];    // block at (q % 3 - 1, q / 3 % 3 - 1, q / 9 - 1), or kUnknown
    std::int32_t xs;        // crossing slots of the block, or kNone
    std::uint64_t xwant[3];  // edges from the points along each axis to compute (scratch)
    std::uint32_t node[64];  // index of the point's node, where present
    // A crossed cell's configuration, as its last walk found it: every move is followed
    // by update_surface, which walks the cells round the moved point again.
    std::uint8_t cfg[64];
  };
  static constexpr std::uint32_t kNoCrossing = 0xFFFFFFFFu;
  Lattice() = default;
  static int local(int li, int lj, int lk) { return li | lj << 2 | lk << 4; }
  static int local(Key p) { return int((p & 3) | (p >> 21 & 3) << 2 | (p >> 42 & 3) << 4); }
  std::size_t block_count() const { return blocks_.size(); }
  Block& blk(std::int32_t b) { return blocks_[std::size_t(b)]; }
  const Block& blk(std::int32_t b) const { return blocks_[std::size_t(b)]; }
  Key point(std::int32_t b, int l) const {
    const Block& B = blk(b);
    return key(B.bi * 4 + (l & 3), B.bj * 4 + (l >> 2 & 3), B.bk * 4 + (l >> 4));
  }
  std::int32_t find_block(int bi, int bj, int bk) const { return table_.find(key(bi, bj, bk)); }
  std::int32_t block_of(Key p) const { return find_block(ki(p) >> 2, kj(p) >> 2, kk(p) >> 2); }
  /// The block (created when missing; serial only).
  std::int32_t block(int bi, int bj, int bk) {
    bool inserted = false;
    const std::int32_t b = table_.find_or_insert(key(bi, bj, bk), std::int32_t(blocks_.size()), inserted);
    if (!inserted) return b;
    Block B;
    B.bi = bi, B.bj = bj, B.bk = bk;
    B.present = B.surface = B.mark = B.mark2 = 0;
    B.xs = kNone;
    B.xwant[0] = B.xwant[1] = B.xwant[2] = 0;
    std::fill(std::begin(B.nb), std::end(B.nb), kUnknown);
    B.nb[13] = b;
    blocks_.push_back(B);
    return b;
  }
  /// Neighbour q of block b (as in Block::nb), kNone when there is none. Safe in
  /// parallel with other readers: the link only ever changes from kUnknown to a block.
  std::int32_t neighbour(std::int32_t b, int q) const {
    const std::int32_t n = __atomic_load_n(&blk(b).nb[q], __ATOMIC_RELAXED);
    if (n >= 0) return n;
    const Block& B = blk(b);
    const std::int32_t f = find_block(B.bi + q % 3 - 1, B.bj + q / 3 % 3 - 1, B.bk + q / 9 - 1);
    if (f >= 0) __atomic_store_n(&const_cast<Block&>(B).nb[q], f, __ATOMIC_RELAXED);
    return f;
  }
  /// Block and local index of the point (li, lj, lk) given relative to block b (each in
  /// [-4, 8)); the block is kNone when missing.
  std::pair<std::int32_t, int> rel(std::int32_t b, int li, int lj, int lk) const {
    const int q = ((li >> 2) + 1) + ((lj >> 2) + 1) * 3 + ((lk >> 2) + 1) * 9;
    return {q == 13 ? b : neighbour(b, q), local(li & 3, lj & 3, lk & 3)};
  }
  /// As rel, creating the block when missing (serial only).
  std::pair<std::int32_t, int> rel_get(std::int32_t b, int li, int lj, int lk) {
    const int q = ((li >> 2) + 1) + ((lj >> 2) + 1) * 3 + ((lk >> 2) + 1) * 9;
    std::int32_t n = q == 13 ? b : neighbour(b, q);
    if (n < 0) {
      const Block& B = blk(b);
      n = block(B.bi + q % 3 - 1, B.bj + q / 3 % 3 - 1, B.bk + q / 9 - 1);
      blk(b).nb[q] = n;
    }
    return {n, local(li & 3, lj & 3, lk & 3)};
  }
  bool present(std::int32_t b, int l) const { return b >= 0 && (blk(b).present >> l & 1); }
  Node& node(std::int32_t b, int l) { return nodes_[blk(b).node[l]]; }
  const Node& node(std::int32_t b, int l) const { return nodes_[blk(b).node[l]]; }
  Node* find(Key p) {
    const std::int32_t b = block_of(p);
    const int l = local(p);
    return present(b, l) ? &node(b, l) : nullptr;
  }
  const Node* find(Key p) const { return const_cast<Lattice*>(this)->find(p); }
  Node& at(Key p) {
    Node* n = find(p);
    if (!n) throw std::out_of_range("extract_dmc: internal error: lattice point not evaluated");
    return *n;
  }
  const Node& at(Key p) const { return const_cast<Lattice*>(this)->at(p); }
  /// Enters the point's node; false (nothing changed) when it was there.
  bool enter(std::int32_t b, int l, const Node& v) {
    Block& B = blk(b);
    if (B.present >> l & 1) return false;
    B.present |= std::uint64_t(1) << l;
    B.node[l] = std::uint32_t(nodes_.size());
    nodes_.push_back(v);
    return true;
  }
  bool emplace(Key p, const Node& v) { return enter(block(ki(p) >> 2, kj(p) >> 2, kk(p) >> 2), local(p), v); }
  /// Room for n more nodes, so that claim_point may run in parallel.
  void reserve_nodes(std::size_t n) { nodes_.reserve_more(n); }
  /// Enters point l of block b when this call is the first to claim it (parallel, after
  /// reserve_nodes): its node is returned, to be filled in; nullptr when it was there.
  Node* claim_point(std::int32_t b, int l) {
    Block& B = blk(b);
    if (!set_bit(B.present, l)) return nullptr;
    const std::size_t i = nodes_.claim();
    B.node[l] = std::uint32_t(i);
    return &nodes_[i];
  }
  /// Sets a bit of a mask shared between threads: true for the one caller that set it
  /// (a plain load first: most bits asked for are set already).
  static bool set_bit(std::uint64_t& mask, int bit) {
    const std::uint64_t m = std::uint64_t(1) << bit;
    if (__atomic_load_n(&mask, __ATOMIC_RELAXED) & m) return false;
    return !(__atomic_fetch_or(&mask, m, __ATOMIC_RELAXED) & m);
  }
  /// The crossing on the lattice edge from point l of block b along axis a, or nullptr.
  Crossing* crossing(std::int32_t b, int l, int a) {
    const std::int32_t xs = blk(b).xs;
    if (xs < 0) return nullptr;
    const std::uint32_t e = xslots_[std::size_t(xs)][std::size_t(l * 3 + a)];
    return e == kNoCrossing ? nullptr : &crossings_[e];
  }
  const Crossing* crossing(std::int32_t b, int l, int a) const { return const_cast<Lattice*>(this)->crossing(b, l, a); }
  /// Index of the crossing on the lattice edge from point l of block b along axis a, or
  /// kNoCrossing.
  std::uint32_t crossing_index(std::int32_t b, int l, int a) const {
    const std::int32_t xs = blk(b).xs;
    return xs < 0 ? kNoCrossing : xslots_[std::size_t(xs)][std::size_t(l * 3 + a)];
  }
  /// Edge key (point * 3 + axis) form.
  Crossing* crossing(Key ek) {
    const Key p = ek / 3;
    const std::int32_t b = block_of(p);
    return b < 0 ? nullptr : crossing(b, local(p), int(ek % 3));
  }
  /// Gives block b its crossing slots (serial).
  void make_slots(std::int32_t b) {
    Block& B = blk(b);
    if (B.xs >= 0) return;
    B.xs = std::int32_t(xslots_.size());
    std::array<std::uint32_t, 192> none;
    none.fill(kNoCrossing);
    xslots_.push_back(none);
  }
  /// Room for n more refined crossings (feature_step), so that claim_refined may run in
  /// parallel.
  void reserve_refined(std::size_t n) { refined_.reserve_more(n); }
  std::int32_t claim_refined() { return std::int32_t(refined_.claim()); }
  Crossing& refined(std::int32_t r) { return refined_[std::size_t(r)]; }
  const Crossing& refined(std::int32_t r) const { return refined_[std::size_t(r)]; }
  /// Room for n more crossings, so that claim_crossing may run in parallel.
  void reserve_crossings(std::size_t n) { crossings_.reserve_more(n); }
  /// The slot of the crossing on edge (l, a) of block b (which has slots).
  std::uint32_t& slot(std::int32_t b, int l, int a) { return xslots_[std::size_t(blk(b).xs)][std::size_t(l * 3 + a)]; }
  Crossing& crossing_at(std::uint32_t e) { return crossings_[e]; }
  /// A new crossing (parallel, after reserve_crossings).
  std::uint32_t claim_crossing() { return std::uint32_t(crossings_.claim()); }
  std::size_t crossing_count() const { return crossings_.size(); }
  bool is_surface(Key c) const {
    const std::int32_t b = block_of(c);
    return b >= 0 && (blk(b).surface >> local(c) & 1);
  }
  std::vector<Key> surface_list() const {
    std::vector<Key> out;
    for (std::size_t b = 0; b < blocks_.size(); ++b)
      for (std::uint64_t m = blocks_[b].surface; m; m &= m - 1) out.push_back(point(std::int32_t(b), __builtin_ctzll(m)));
    return out;
  }

 private:
  Chunked<Block> blocks_;
  Chunked<Node> nodes_;
  Chunked<std::array<std::uint32_t, 192>> xslots_;
  Chunked<Crossing> crossings_;
  Chunked<Crossing> refined_;
  static_assert(kNone == detail::BlockTable::kAbsent, "a missing block reads as kNone");
  detail::BlockTable table_;
};

// Where a lattice point moves (feature step).
struct Proposal {
  Key node;
  int priority;  // 1 corner, 0 edge
  Key cell;
  Vec3d pos;    // on the feature
  Vec3d nudge;  // tiny step into the solid
  double length;  // edge: length of the line inside the point's Omega (longer wins)
};

class Dmc {
 public:
  Dmc(const ImplicitFunction& f, const Aabb& box, int resolution, const DmcOptions& opt)
      : f_(f), opt_(opt), arena_(worker_threads(opt.threads)) {
    if (opt.window) {
      // A window of a larger lattice: its points are the global ones shifted by the
      // offset (every face of the window is fixed: the lattice there is shared).
      // With a halo, the lattice reaches that many cells below the lower faces.
      h_ = opt.window->h;
      for (int a = 0; a < 3; ++a) {
        const std::size_t u = std::size_t(a);
        halo_[a] = std::clamp(opt.halo[u], 0, opt.window->offset[u]);
        n_[a] = opt.window->cells[u] + halo_[a];
        off_[a] = opt.window->offset[u] - halo_[a];
      }
      origin_ = opt.window->origin;
      lo_ = origin_ + h_ * Vec3d(off_[0], off_[1], off_[2]);
    } else {
      lo_ = origin_ = box.min.cast<double>();
      const Vec3d ext = (box.max - box.min).cast<double>();
      h_ = ext.maxCoeff() / resolution;
      for (int a = 0; a < 3; ++a) n_[a] = std::max(1, int(std::ceil(ext[a] / h_ - 1e-9)));
    }
    const double s = opt.search_step > 0 ? opt.search_step : h_ / 5;
    m_ = std::clamp(int(std::lround(h_ / s)), 1, 16);
    st_.cell_size = h_;
    st_.search_step = h_ / m_;
  }

  Mesh run(DmcStats* stats);

 private:
  // ---------------------------------------------------------------- evaluation
  double g(const Vec3d& x) const { return f_.value(x) - opt_.iso; }
  // The global lattice's point (the same double in every window holding it).
  Vec3d upos(Key p) const { return origin_ + h_ * Vec3d(off_[0] + ki(p), off_[1] + kj(p), off_[2] + kk(p)); }
  // A new node for lattice point k: undeformed, or, for a fixed point an earlier block
  // moved (DmcOptions::given), there with its value (then true: not to be evaluated).
  bool make_node(Key k, Node& out) const {
    const std::uint8_t flags = on_boundary(k) ? kFixed : 0;
    if (flags && opt_.given)
      if (const auto it = opt_.given->find(global_key(k)); it != opt_.given->end()) {
        out = Node{it->second.pos, it->second.value, std::uint8_t(it->second.flags | kFixed)};
        return true;
      }
    out = Node{upos(k), 0.0, flags};
    return false;
  }
  // Whether fixed point k was given by an earlier block (its node holds the value).
  bool is_given(Key k, const Node& nd) const {
    return (nd.flags & kFixed) && opt_.given && opt_.given->count(global_key(k));
  }
  std::uint64_t global_key(Key k) const { return lattice_edge_key(off_[0] + ki(k), off_[1] + kj(k), off_[2] + kk(k), 3); }
  // Whether cell (i, j, k) lies in the halo (its faces are not emitted).
  bool in_halo(int i, int j, int k) const { return i < halo_[0] || j < halo_[1] || k < halo_[2]; }
  bool on_boundary(Key p) const {
    const int i = ki(p), j = kj(p), k = kk(p);
    return i == 0 || j == 0 || k == 0 || i == n_[0] || j == n_[1] || k == n_[2];
  }
  bool node_in_grid(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i <= n_[0] && j <= n_[1] && k <= n_[2];
  }
  bool cell_in_grid(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < n_[0] && j < n_[1] && k < n_[2];
  }

  template <class Fn>
  void parallel(std::size_t count, Fn&& fn) {
    arena_.execute([&] { tbb::parallel_for(std::size_t(0), count, fn); });
  }

  // The crossed cells in key order (keys are unique: the same order for any thread count).
  std::vector<Key> sorted_surface() {
    std::vector<Key> cells = nodes_.surface_list();
    arena_.execute([&] { tbb::parallel_sort(cells.begin(), cells.end()); });
    return cells;
  }

  // Evaluates the missing lattice points of `keys` (undeformed positions) in parallel.
  // The new points are entered first (value filled in below), which also drops
  // duplicates without sorting; `keys` keeps the new ones.
  void ensure(std::vector<Key>& keys);
  // f at xs[i] into out[i], in parallel, consecutive points of one block (block_of(i))
  // taken together by values_near (the same values as value()), at most 192 at a time.
  template <class BlockOf>
  void values_by_block(const std::vector<Vec3d>& xs, std::vector<double>& out, BlockOf&& block_of) {
    out.resize(xs.size());
    std::vector<std::size_t> runs;
    for (std::size_t i = 0; i < xs.size(); ++i)
      if (i == 0 || block_of(i) != block_of(i - 1) || i - runs.back() >= 192) runs.push_back(i);
    runs.push_back(xs.size());
    parallel(runs.size() - 1, [&](std::size_t r) {
      f_.values_near(xs.data() + runs[r], int(runs[r + 1] - runs[r]), out.data() + runs[r]);
    });
  }

  // Lattice values of the entered points `fresh` (block << 6 | local index), in
  // parallel, a block's points taken together (values_near; the same values).
  void evaluate(std::vector<std::uint32_t> fresh);
  double lattice_value(const Vec3d& pos, std::uint8_t flags) const {
    return lattice_value_from(f_.value(pos), flags, pos);
  }
  // The lattice value from f at the point `pos` (a fixed point sits on its lattice point).
  double lattice_value_from(double f, std::uint8_t flags, const Vec3d& pos) const {
    double x = f - opt_.iso;
    if (!std::isfinite(x)) x = h_;  // NaN counts as outside
    if (opt_.close_at_box && (flags & kFixed) && on_outer_layer(pos)) x = std::max(x, 0.5 * h_);
    return x;
  }
  // Whether the fixed lattice point at `pos` is on the outermost layer of the whole
  // lattice (the box's, or with a window the global lattice's, not the window's faces).
  bool on_outer_layer(const Vec3d& pos) const {
    if (!opt_.window) return true;  // every fixed point is on the box's faces
    for (int a = 0; a < 3; ++a) {
      const long g = std::lround((pos[a] - lo_[a]) / h_) + off_[a];
      if (g == 0 || g == opt_.window->global_cells[std::size_t(a)]) return true;
    }
    return false;
  }
  // Configuration of cell l of block b (corner q inside: bit q), through the links.
  int config(std::int32_t b, int l) const;
  int config(Key c) const { return config(nodes_.block_of(c), Lattice::local(c)); }
  // Whether cell edge e has a sign change, from the cell's configuration.
  static bool crossed(int cfg, int e) {
    const auto& ec = mc::edge_corners();
    return ((cfg >> ec[e][0]) ^ (cfg >> ec[e][1])) & 1;
  }

  // ---------------------------------------------------------------- traversal
  std::vector<Key> seed_cells();

  // A scan line's value at lattice point (i, j, k), or nullptr when the point is on none.
  const double* scan_value(int i, int j, int k) const {
    if (scan_step_ == 0 || j % scan_step_ || k % scan_step_ || !node_in_grid(i, j, k)) return nullptr;
    return &scan_[(std::size_t(k / scan_step_) * std::size_t(scan_nj_) + std::size_t(j / scan_step_)) *
                      (std::size_t(n_[0]) + 1) + std::size_t(i)];
  }
  // Lattice point p as the neighbour tests see it: its node, or, for a point of a scan
  // line that has none, a node made in `tmp` (undeformed, its scan-line value); nullptr
  // when it was never evaluated.
  const Node* known(Key p, Node& tmp) const {
    if (const Node* n = nodes_.find(p)) return n;
    const double* v = scan_value(ki(p), kj(p), kk(p));
    if (!v) return nullptr;
    tmp = Node{upos(p), *v, std::uint8_t(on_boundary(p) ? kFixed : 0)};
    return &tmp;
  }


  // Surface tracking from the cells `start`, on the block lattice (cells as block << 6 |
  // local index, neighbours through the links); crossed cells get their surface bit,
  // cells that have it are not revisited. probe_first: a seed cell the surface misses
  // probes its 26 neighbours once. Parallel as marching_cubes.cpp's walk: the corners
  // and the visited cells (mark bits) are claimed atomically; blocks are created only in
  // the serial parts (a step into a block not there yet is deferred to them). The set
  // of crossed cells does not depend on the order of a wave.
  void traverse(const std::vector<std::uint64_t>& start, bool probe_first);
  // Claims cell l of block b for the walk (parallel): false when it is a crossed cell
  // already or visited; a block whose first mark bit this sets goes to `marked`.
  bool visit(std::int32_t b, int l, std::vector<std::int32_t>& marked);

  // After lattice points moved: only the cells having one as a corner can change; they
  // are re-examined and the walk continues from them into cells not yet known.
  void update_surface(const std::vector<Key>& moved);

  // ---------------------------------------------------------------- step 1
  // Samples Omega of lattice point p at step h/m; returns true and the new position and
  // value when samples of the wanted sign (inside when want_inside) exist: their
  // centroid, or, where the centroid itself has the wrong sign (a non-convex part), the
  // wanted sample nearest to it.
  bool search(Key p, bool want_inside, Vec3d& pos, double& value) const;

  // The lattice value of p's neighbour `step` (+-1) along `axis` (p is point l of block
  // b), through the links: its node's, or its scan line's; false when it was never
  // evaluated or is outside the grid.
  bool neighbour_value(Key p, std::int32_t b, int l, int axis, int step, double& v) const;

  // The lattice values of p's six neighbours (q = 2 * axis + (step > 0)), read once for
  // both first-wave tests; has[q] false where neighbour_value has none.
  struct Neighbours {
    double v[6];
    bool has[6];
  };
  void neighbour_values(Key p, std::int32_t b, int l, Neighbours& nb) const {
    for (int q = 0; q < 6; ++q) nb.has[q] = neighbour_value(p, b, l, q / 2, q % 2 ? 1 : -1, nb.v[q]);
  }
  // First-wave pruning from the lattice values alone (no evaluation): a point whose |f|
  // exceeds 1.5 * 1.3 h times the largest difference quotient to its evaluated
  // 6-neighbours is too far from the surface for its Omega to reach it.
  static bool cheap_candidate(const Node& nd, const Neighbours& nb, double h);

  // grad f at lattice point p from the lattice values alone: central differences with
  // its evaluated 6-neighbours (one-sided where one side is missing); false when an
  // axis has neither. Only before any point moved (the differences assume undeformed
  // neighbours): the first wave's probe direction.
  static constexpr double kLinear = 3, kTangent = 0.25;
  bool lattice_gradient(const Node& nd, const Neighbours& nb, Vec3d& gr) const;
  // The first wave's probe answered from the lattice where it can be (no evaluation):
  // along the axis nearest the lattice gradient gr, towards the near surface, every
  // evaluated lattice point from the first past that surface (|f| / |gr| away along
  // gr) to the first at least one h past it, measured along gr, lies on the other
  // side. Then the part (or gap) beyond the near surface is at least as thick there
  // as the probe asks, and the point is done. False (probe it) where a lattice point
  // on the way is on its side or was never evaluated, or more than kThickSteps steps
  // are needed.
  static constexpr int kThickSteps = 4;
  bool lattice_thick(Key p, std::int32_t b, int l, const Node& nd, const Vec3d& gr) const;

  // How far from its lattice point Omega reaches towards a plane of unit normal n
  // (h/2 |n|_1), plus kReachSlack h for the first-order distance's error: a point whose
  // near surface (|f| / |grad f| away along n) lies beyond has no sample of the other
  // side in Omega, and its search would find nothing.
  static constexpr double kReachSlack = 0.25;
  double omega_reach(const Vec3d& n) const { return h_ * (0.5 * n.cwiseAbs().sum() + kReachSlack); }

  enum Role : char { kSkip, kMove, kPass };
  // The pruning of a later wave's candidate (see barycentre_step): whether its Omega
  // is searched (mover: its near surface within omega_reach) or it passes the flood on
  // (passer). One gradient and, for a passer within the band, one probe evaluation one
  // h away from the near surface (movers next to a moved point follow the paper's
  // flood; the first wave's probe is probe_first_wave).
  bool probe(const Node& nd, char role) const;

  // The first wave's pruning (a mover is searched where the part beyond its near
  // surface is thin: a probe one h past that surface is back on its side), for the
  // candidates of one block, in two rounds. First with the lattice's gradient
  // (lattice_gradient; no evaluation but the probe): a candidate it finds thick (or
  // beyond 1.3 h) is done. The others (thin there, or no lattice gradient) take the
  // probe with f's gradient, which decides. Each round's gradients and probes are
  // taken together (ImplicitFunction::*_near: one octree walk for the lot on the MPU
  // surface).
  struct ProbeBatch {
    std::vector<const Node*> nodes;
    std::vector<Key> keys;
    std::vector<Vec3d> grads, probes, xs, exact_grads;
    std::vector<double> values;
    std::vector<int> probe_of, lattice, exact, thin;
    std::vector<char> has_grad;
    void clear() {
      nodes.clear();
      keys.clear();
      grads.clear();
      has_grad.clear();
    }
  };
  // One round over batch.nodes[at[i]] with gradients grads[at[i]]: the candidates whose
  // probe says thin (or whose gradient is unusable) go to `thin`.
  void probe_round(ProbeBatch& batch, const std::vector<int>& at, std::vector<int>& thin) const;
  // Counts: probes taken, f's gradients taken.
  void probe_first_wave(ProbeBatch& batch, std::vector<Key>& todo, std::size_t& probes, std::size_t& gradients) const;

  // The first wave of the flood, in parallel over the blocks: the corners of the crossed
  // cells, each once (mark bits claimed atomically, cleared after), pre-tested and
  // probed a block at a time; the points whose Omega is to be searched, in key order.
  std::vector<Key> first_wave_todo();

  // The paper's flood with pruning. Candidates are the corners of the crossed cells,
  // then the 26-neighbours of the points that moved (or of points already on the thin
  // part's side, which the flood passes through). A candidate is looked at only when
  // the surface may pass through its Omega (|f| / |grad f| within 1.3 h) and the part
  // beyond that surface is thin: a probe one h past the nearest surface point along
  // -grad f (+grad f for a point inside) is back on the candidate's side (the first
  // wave asks the lattice's gradient first, probe_first_wave). Only then is
  // Omega sampled (m^3 evaluations). A point already inside a thin part (for the
  // thin-gap flood: outside in a thin gap) passes the flood on when the other side is
  // within h too.
  std::vector<Key> barycentre_step();

  // Moved points that are neighbours only across a cell edge or corner would stay apart
  // in MC (ambiguous faces keep inside corners apart): where the segment between them
  // lies in the part (gap), the lattice points whose Omega it crosses move onto it.
  void bridge(std::vector<Key>& moved);

  // A few moved points that touch no unmoved point of their new sign (6-neighbours)
  // would be a speck of their own: slivers of a convex edge or corner cut off by an
  // Omega, not a thin part (which floods into many points). They move back.
  void prune_islands(std::vector<Key>& moved);

  // ---------------------------------------------------------------- crossings
  // The crossings on the deformed lattice edges from a[i] to b[i] (i < n, edges close
  // together: one block's), each by Illinois regula falsi on f along the edge, keeping
  // the bracket, up to `steps` evaluations; the edges step together so that each
  // round's values and gradients are taken together (ImplicitFunction::
  // values_gradients_near: one octree walk for both on the MPU surface). Each edge's
  // sequence is what it would be alone. The next point is the Newton step along the
  // edge while it stays in the bracket and its estimated error is under kNewtonTrust,
  // else the Illinois step. The normal is grad f at the edge's last evaluation: at the
  // crossing itself where that value was at round-off, else one step short of it (a
  // tiny fraction of h; the vertex is the stepped point). Edges never evaluated (none
  // when steps > 0) take gradients_near at the crossing.
  struct CrossingBatch {
    struct State {
      double fa, fb, lo, hi, t, tol;
      int side, evals;
      bool done;
    };
    std::vector<State> state;
    std::vector<Vec3d> xs, grads, last_grads, at;
    std::vector<double> values;
    std::vector<int> active;
  };
  // `done_error`: the estimated error (fraction of the edge) below which a Newton step
  // ends the refinement (0: only round-off does). Returns the gradients taken.
  std::size_t crossings(const Node* const* a, const Node* const* b, int n, int steps, double done_error, CrossingBatch& cb,
                 Crossing* out) const;

  // One block's edges to cross: ends and where each result goes.
  struct EdgeBatch {
    std::vector<const Node*> a, b;
    std::vector<Crossing*> out;
    std::vector<Crossing> result;
    CrossingBatch work;
    void clear() {
      a.clear();
      b.clear();
      out.clear();
    }
    void add(const Node* from, const Node* to, Crossing* where) {
      a.push_back(from);
      b.push_back(to);
      out.push_back(where);
    }
  };
  // Crosses the batch's edges and stores the crossings; returns the values of f taken
  // and adds the gradients taken to `gradients`.
  static constexpr double kNewtonDone = 1e-4;   // mesh crossings: done at 1e-4 of the edge
  static constexpr double kNewtonTrust = 1e-2;  // Newton trusted up to 1e-2 of the edge
  // The walk's reach beyond the trust distance with the untrusted surface dropped, in
  // cells from a cell's centre: DMC moves lattice points up to h / 2 an axis, so a
  // kept face lies within sqrt 3 h of its cell's centre, and a neighbour sharing one of
  // its points within 2 sqrt 3 h; one cell more of slack. A thin-part search that
  // starts in a cell beyond that is not made: meshes the same on the dragon and the
  // Kinect scene and in the tests, not a guarantee (docs/run.md).
  static constexpr double kPruneReach = 2 * 1.7320508075688772 + 1;
  // With the untrusted surface dropped: x lies beyond the walk's reach (the walk and
  // the thin-part floods stop there).
  bool beyond_reach(const Vec3d& x) const {
    return opt_.untrusted == UntrustedRegions::kLeaveOpen && !f_.may_be_trusted_near(x, kPruneReach * h_);
  }
  static constexpr double kLocated = 1e-9;      // a crossing this close (of the edge) is done
  std::size_t solve(EdgeBatch& eb, int steps, double done_error, std::size_t& gradients) const;

  void mark_stale(Key ek) {
    if (Crossing* e = nodes_.crossing(ek)) e->stale = true;
  }

  // Crossings (and normals) of every crossed edge of the surface cells not yet known
  // (or stale). In parallel: the cells mark their crossed edges in the block of the
  // edge's lower end (xwant bits, claimed atomically); each such block then computes
  // its marked edges' crossings (new ones get an index claimed atomically; the order of
  // the crossings in storage is not used).
  // Marks the crossed edges of cell (b, l) as wanted: each edge's bit goes to
  // the block of its lower end (xwant, one word per axis).
  void want_crossings(std::int32_t b, int l);

  void compute_crossings();

  // ---------------------------------------------------------------- step 2
  // Per crossed cell: sharp edge / corner from the crossing normals; proposals for the
  // lattice points to move.
  // Run twice (feature_step): first (refined false) it only tells whether the cell's
  // crossings suggest a feature (then they are refined to round-off, each edge once, and
  // kept in Crossing::refined); then, for those cells, it finds the feature.
  bool detect(Key c, std::vector<Proposal>& out, bool refined) const;

  // The crossings of the cells that suggest a feature, refined to round-off (up to 60
  // steps), each edge once (a crossing is shared by up to four cells): marked by the
  // cells in the block of the edge's lower end (xwant bits), computed per block in
  // parallel.
  void refine_sharp(const std::vector<Key>& cells, const std::vector<char>& sharp);

  std::vector<Key> feature_step();

  // Where the chain of points on an edge turns a lattice corner, the outside point in
  // the turn, next to the body, would leave a tunnel between chain and body (a handle).
  // It moves to the inside sample of its Omega nearest to its chain neighbours.
  void fill_turns(std::vector<Key>& moved);

  // ---------------------------------------------------------------- step 3
  Mesh build_mesh();

  void drop_untrusted(Mesh& mesh, std::vector<std::uint64_t>* keys);

  const ImplicitFunction& f_;
  const DmcOptions& opt_;
  mutable std::atomic<std::size_t> smooth_cells_{0};  // detect(): cells left alone as smooth
  tbb::task_arena arena_;
  Vec3d lo_;      // the lattice's first point
  Vec3d origin_;  // the global lattice's first point (lo_ without a window)
  double h_ = 0;
  int n_[3] = {1, 1, 1};
  int off_[3] = {0, 0, 0};  // the lattice's offset in the global lattice (vertex_edges)
  int halo_[3] = {0, 0, 0};  // cells below the window's lower faces (DmcOptions::halo)
  int m_ = 5;
  DmcStats st_;
  Lattice nodes_;
  std::unordered_map<Key, double> original_;  // value before step 1 moved the point
  // Scan lines (no seeds): f along x at every scan_step_-th j and k, kept apart from the
  // nodes (no blocks for them, as in MC); the neighbour tests see them as evaluated
  // points (known()), and a node entered on a line takes its value.
  int scan_step_ = 0, scan_nj_ = 0;
  std::vector<double> scan_;
};

}  // namespace station::detail::dmc
