#include "reconstruct/dmc.h"

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
#include "reconstruct/detail/lattice_storage.h"
#include "reconstruct/detail/mc_tables.h"
#include "reconstruct/mpu.h"

namespace station {
namespace {

// Lattice point / cell key: 21 bits per axis (as in marching_cubes.cpp).
using Key = std::uint64_t;
Key key(std::int64_t i, std::int64_t j, std::int64_t k) { return Key(i) | Key(j) << 21 | Key(k) << 42; }
int ki(Key k) { return int(k & 0x1FFFFF); }
int kj(Key k) { return int(k >> 21 & 0x1FFFFF); }
int kk(Key k) { return int(k >> 42 & 0x1FFFFF); }
// std::lround (halves away from zero) without the library call for lattice
// coordinates in [0, 2^31): truncation is the floor there and y - floor(y) is exact.
std::int64_t round_coordinate(double y) {
  if (!(y >= 0 && y < 2147483648.0)) return std::lround(y);
  const std::int64_t t = std::int64_t(y);
  return t + (y - double(t) >= 0.5 ? 1 : 0);
}
Key corner_key(Key cell, int q) { return key(ki(cell) + (q & 1), kj(cell) + (q >> 1 & 1), kk(cell) + (q >> 2 & 1)); }

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
  bool is_surface(Key c) const {
    const std::int32_t b = block_of(c);
    return b >= 0 && (blk(b).surface >> local(c) & 1);
  }
  void set_surface(Key c, bool on) {
    const std::int32_t b = on ? block(ki(c) >> 2, kj(c) >> 2, kk(c) >> 2) : block_of(c);
    if (b < 0) return;
    const std::uint64_t m = std::uint64_t(1) << local(c);
    if (on) blk(b).surface |= m;
    else blk(b).surface &= ~m;
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
      : f_(f), opt_(opt), arena_(opt.threads == 0 ? tbb::this_task_arena::max_concurrency() : opt.threads) {
    lo_ = box.min.cast<double>();
    const Vec3d ext = (box.max - box.min).cast<double>();
    h_ = ext.maxCoeff() / resolution;
    for (int a = 0; a < 3; ++a) n_[a] = std::max(1, int(std::ceil(ext[a] / h_ - 1e-9)));
    const double s = opt.search_step > 0 ? opt.search_step : h_ / 5;
    m_ = std::clamp(int(std::lround(h_ / s)), 1, 16);
    st_.cell_size = h_;
    st_.search_step = h_ / m_;
  }

  Mesh run(DmcStats* stats) {
    using Clock = std::chrono::steady_clock;
    auto since = [](Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); };
    auto t0 = Clock::now();
    {
      std::vector<std::uint64_t> start;
      for (Key c : seed_cells())
        start.push_back(std::uint64_t(nodes_.block(ki(c) >> 2, kj(c) >> 2, kk(c) >> 2)) << 6 | std::uint64_t(Lattice::local(c)));
      traverse(start, !opt_.seeds.empty());
    }
    st_.seconds_traversal = since(t0);

    t0 = Clock::now();
    std::vector<Key> moved;
    if (opt_.barycentre || opt_.thin_gaps) moved = barycentre_step();
    if (!moved.empty()) update_surface(moved);
    st_.seconds_barycentre = since(t0);
    t0 = Clock::now();

    bool crossings_done = false;
    if (opt_.features) {
      compute_crossings();
      std::vector<Key> fmoved = feature_step();
      crossings_done = fmoved.empty();
      if (!fmoved.empty()) {
        update_surface(fmoved);
        // Crossings on the edges of moved points are stale.
        for (Key p : fmoved)
          for (int a = 0; a < 3; ++a) {
            mark_stale(p * 3 + a);
            const int i = ki(p), j = kj(p), k = kk(p);
            const int d[3] = {i - (a == 0), j - (a == 1), k - (a == 2)};
            if (d[0] >= 0 && d[1] >= 0 && d[2] >= 0) mark_stale(key(d[0], d[1], d[2]) * 3 + a);
          }
      }
    }
    st_.seconds_features = since(t0);
    t0 = Clock::now();
    if (!crossings_done) compute_crossings();
    Mesh mesh = build_mesh();
    st_.seconds_mesh = since(t0);
    if (stats) *stats = st_;
    return mesh;
  }

 private:
  // ---------------------------------------------------------------- evaluation
  double g(const Vec3d& x) const { return f_.value(x) - opt_.iso; }
  Vec3d upos(Key p) const { return lo_ + h_ * Vec3d(ki(p), kj(p), kk(p)); }
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
  void ensure(std::vector<Key>& keys) {
    std::size_t m = 0;
    std::vector<std::uint32_t> fresh;
    Key last = ~Key(0);  // block of the previous key (runs of keys share blocks: scan lines)
    std::int32_t b = Lattice::kNone;
    for (Key k : keys) {
      const Key bk = BlockIndex::block_of(k);
      if (bk != last) b = nodes_.block(ki(k) >> 2, kj(k) >> 2, kk(k) >> 2), last = bk;
      const int l = Lattice::local(k);
      if (nodes_.enter(b, l, Node{upos(k), 0.0, std::uint8_t(on_boundary(k) ? kFixed : 0)})) {
        keys[m++] = k;
        fresh.push_back(std::uint32_t(b) << 6 | std::uint32_t(l));
      }
    }
    keys.resize(m);
    evaluate(fresh);
  }
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
  void evaluate(std::vector<std::uint32_t> fresh) {
    std::sort(fresh.begin(), fresh.end());
    std::vector<std::size_t> runs;  // first handle of each block
    for (std::size_t i = 0; i < fresh.size(); ++i)
      if (i == 0 || fresh[i] >> 6 != fresh[i - 1] >> 6) runs.push_back(i);
    runs.push_back(fresh.size());
    tbb::enumerable_thread_specific<std::size_t> count(0);
    parallel(runs.size() - 1, [&](std::size_t r) {
      Vec3d xs[64];
      double vs[64];
      Node* at[64];
      int n = 0;
      for (std::size_t i = runs[r]; i < runs[r + 1]; ++i) {
        const std::int32_t b = std::int32_t(fresh[i] >> 6);
        const int l = int(fresh[i] & 63);
        Node& nd = nodes_.node(b, l);
        const Key p = nodes_.point(b, l);
        if (const double* v = scan_value(ki(p), kj(p), kk(p))) {
          nd.val = *v;
          continue;
        }
        at[n] = &nd;
        xs[n++] = nd.pos;
      }
      f_.values_near(xs, n, vs);
      for (int i = 0; i < n; ++i) at[i]->val = lattice_value_from(vs[i], at[i]->flags);
      count.local() += std::size_t(n);
    });
    for (std::size_t n : count) st_.evaluations += n;
  }
  double lattice_value(const Vec3d& pos, std::uint8_t flags) const { return lattice_value_from(f_.value(pos), flags); }
  // The lattice value from f at the point.
  double lattice_value_from(double f, std::uint8_t flags) const {
    double x = f - opt_.iso;
    if (!std::isfinite(x)) x = h_;  // NaN counts as outside
    if (opt_.close_at_box && (flags & kFixed)) x = std::max(x, 0.5 * h_);
    return x;
  }
  // Configuration of cell l of block b (corner q inside: bit q), through the links.
  int config(std::int32_t b, int l) const {
    const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
    int cfg = 0;
    for (int q = 0; q < 8; ++q) {
      const auto [cb, cl] = nodes_.rel(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
      if (!nodes_.present(cb, cl)) throw std::out_of_range("extract_dmc: internal error: lattice point not evaluated");
      if (nodes_.node(cb, cl).val < 0) cfg |= 1 << q;
    }
    return cfg;
  }
  int config(Key c) const { return config(nodes_.block_of(c), Lattice::local(c)); }
  // Whether cell edge e has a sign change, from the cell's configuration.
  static bool crossed(int cfg, int e) {
    const auto& ec = mc::edge_corners();
    return ((cfg >> ec[e][0]) ^ (cfg >> ec[e][1])) & 1;
  }

  // ---------------------------------------------------------------- traversal
  std::vector<Key> seed_cells() {
    std::vector<Key> cells;
    KeySet seen;
    auto push = [&](int i, int j, int k) {
      if (cell_in_grid(i, j, k) && seen.insert(key(i, j, k))) cells.push_back(key(i, j, k));
    };
    if (!opt_.seeds.empty()) {
      for (const Vec3f& p : opt_.seeds) {
        const Vec3d q = (p.cast<double>() - lo_) / h_;
        if (!q.allFinite() || (q.array() < 0).any() || q.x() >= n_[0] || q.y() >= n_[1] || q.z() >= n_[2]) continue;
        push(int(std::floor(q.x())), int(std::floor(q.y())), int(std::floor(q.z())));
      }
      return cells;
    }
    const int step = opt_.coarse_step > 0 ? opt_.coarse_step : std::max(1, std::max({n_[0], n_[1], n_[2]}) / 32);
    scan_step_ = step;
    scan_nj_ = n_[1] / step + 1;
    const int nk = n_[2] / step + 1;
    const std::size_t len = std::size_t(n_[0]) + 1;
    scan_.assign(std::size_t(nk) * std::size_t(scan_nj_) * len, 0.0);
    parallel(std::size_t(nk) * std::size_t(scan_nj_), [&](std::size_t line) {
      const int j = int(line % std::size_t(scan_nj_)) * step, k = int(line / std::size_t(scan_nj_)) * step;
      for (int i = 0; i <= n_[0]; ++i) {
        const Key p = key(i, j, k);
        scan_[line * len + std::size_t(i)] = lattice_value(upos(p), on_boundary(p) ? kFixed : 0);
      }
    });
    st_.evaluations += scan_.size();
    for (int k = 0; k <= n_[2]; k += step)
      for (int j = 0; j <= n_[1]; j += step)
        for (int i = 0; i < n_[0]; ++i)
          if ((*scan_value(i, j, k) < 0) != (*scan_value(i + 1, j, k) < 0))
            for (int dj = -1; dj <= 0; ++dj)
              for (int dk = -1; dk <= 0; ++dk) push(i, j + dj, k + dk);
    return cells;
  }

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

  // Per configuration: bit 2a + side set when the cell's face (axis a, side) has a sign
  // change (the walk crosses it).
  static const std::array<std::uint8_t, 256>& crossed_faces() {
    static const std::array<std::uint8_t, 256> table = [] {
      std::array<std::uint8_t, 256> t{};
      for (int cfg = 0; cfg < 256; ++cfg)
        for (int a = 0; a < 3; ++a)
          for (int side = 0; side < 2; ++side) {
            int in = 0;
            for (int q = 0; q < 8; ++q)
              if ((q >> a & 1) == side && (cfg >> q & 1)) ++in;
            if (in != 0 && in != 4) t[cfg] |= std::uint8_t(1 << (2 * a + side));
          }
      return t;
    }();
    return table;
  }

  // Surface tracking from the cells `start`, on the block lattice (cells as block << 6 |
  // local index, neighbours through the links); crossed cells get their surface bit,
  // cells that have it are not revisited. probe_first: a seed cell the surface misses
  // probes its 26 neighbours once. Parallel as marching_cubes.cpp's walk: the corners
  // and the visited cells (mark bits) are claimed atomically; blocks are created only in
  // the serial parts (a step into a block not there yet is deferred to them). The set
  // of crossed cells does not depend on the order of a wave.
  void traverse(const std::vector<std::uint64_t>& start, bool probe_first) {
    std::vector<std::uint64_t> frontier, next;
    std::vector<std::int32_t> marked;  // blocks whose mark bits (visited cells) are set
    tbb::enumerable_thread_specific<std::vector<std::uint64_t>> next_local, deferred_local;
    tbb::enumerable_thread_specific<std::vector<std::int32_t>> marked_local;
    tbb::enumerable_thread_specific<std::size_t> evaluated_local(0);
    tbb::enumerable_thread_specific<std::vector<std::pair<std::int32_t, Node*>>> pending_local;
    std::vector<std::pair<std::int32_t, Node*>> pending;
    std::vector<std::size_t> groups;
    for (std::uint64_t c : start) {
      const std::int32_t b = std::int32_t(c >> 6);
      Lattice::Block& B = nodes_.blk(b);
      const int l = int(c & 63);
      if (B.mark >> l & 1) continue;
      if (!B.mark) marked.push_back(b);
      B.mark |= std::uint64_t(1) << l;
      frontier.push_back(std::uint64_t(b) << 6 | std::uint64_t(l));
    }
    const auto& faces_of = crossed_faces();
    bool first = probe_first;
    while (!frontier.empty()) {
      // Blocks holding the wave's corners (serial: blocks are created here) and room for
      // their nodes.
      for (std::uint64_t c : frontier) {
        const std::int32_t b = std::int32_t(c >> 6);
        const int l = int(c & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
        const int hi = int(li == 3) | int(lj == 3) << 1 | int(lk == 3) << 2;
        for (int q = 1; q < 8; ++q)
          if ((q & hi) == q) nodes_.rel_get(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
      }
      nodes_.reserve_nodes(8 * frontier.size());
      // Corners not entered yet, each entered by the thread claiming it (a scan line's
      // value taken over), then the others evaluated a block at a time (f.values_near:
      // the MPU surface walks its octree once per group; the same values).
      parallel(frontier.size(), [&](std::size_t fi) {
        const std::uint64_t c = frontier[fi];
        const std::int32_t b = std::int32_t(c >> 6);
        const int l = int(c & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
        auto& mine = pending_local.local();
        for (int q = 0; q < 8; ++q) {
          const auto [cb, cl] = nodes_.rel(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
          Node* nd = nodes_.claim_point(cb, cl);
          if (!nd) continue;
          const Key k = nodes_.point(cb, cl);
          const std::uint8_t flags = on_boundary(k) ? kFixed : 0;
          *nd = Node{upos(k), 0.0, flags};
          if (const double* v = scan_value(ki(k), kj(k), kk(k))) {
            nd->val = *v;
          } else {
            mine.emplace_back(cb, nd);
          }
        }
      });
      pending.clear();
      for (auto& v : pending_local) {
        pending.insert(pending.end(), v.begin(), v.end());
        v.clear();
      }
      // Unique pairs: one order for the same pairs, whatever the thread count.
      arena_.execute([&] {
        tbb::parallel_sort(pending.begin(), pending.end(), [](const auto& x, const auto& y) {
          return x.first != y.first ? x.first < y.first : std::less<const Node*>()(x.second, y.second);
        });
      });
      groups.clear();
      for (std::size_t i = 0; i < pending.size(); ++i)
        if (i == 0 || pending[i].first != pending[i - 1].first) groups.push_back(i);
      groups.push_back(pending.size());
      parallel(groups.size() - 1, [&](std::size_t g) {
        Vec3d xs[64];
        double vs[64];
        for (Vec3d& x : xs) x.setZero();
        const std::size_t first = groups[g];
        const int count = int(groups[g + 1] - first);
        for (int t = 0; t < count; ++t) xs[t] = pending[first + std::size_t(t)].second->pos;
        f_.values_near(xs, count, vs);
        for (int t = 0; t < count; ++t) {
          Node& nd = *pending[first + std::size_t(t)].second;
          nd.val = lattice_value_from(vs[t], nd.flags);
        }
        evaluated_local.local() += std::size_t(count);
      });
      st_.cells_visited += frontier.size();
      // Crossed cells pass the walk on (mark bits claimed atomically).
      const bool probing = first;
      parallel(frontier.size(), [&](std::size_t fi) {
        const std::uint64_t c = frontier[fi];
        const std::int32_t b = std::int32_t(c >> 6);
        const int l = int(c & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
        Lattice::Block& B = nodes_.blk(b);
        const int i = B.bi * 4 + li, j = B.bj * 4 + lj, k = B.bk * 4 + lk;
        auto push = [&](int dx, int dy, int dz) {
          if (!cell_in_grid(i + dx, j + dy, k + dz)) return;
          const auto [nb, nl] = nodes_.rel(b, li + dx, lj + dy, lk + dz);
          if (nb < 0) {  // the block is not there yet
            deferred_local.local().push_back(c << 5 | std::uint64_t((dx + 1) + (dy + 1) * 3 + (dz + 1) * 9));
            return;
          }
          if (visit(nb, nl, marked_local.local())) next_local.local().push_back(std::uint64_t(nb) << 6 | std::uint64_t(nl));
        };
        const std::uint64_t m = std::uint64_t(1) << l;
        const int cfg = config(b, l);
        if (cfg == 0 || cfg == 255) {
          __atomic_fetch_and(&B.surface, ~m, __ATOMIC_RELAXED);
          if (probing)
            for (int q = 0; q < 27; ++q)
              if (q != 13) push(q % 3 - 1, q / 3 % 3 - 1, q / 9 - 1);
          return;
        }
        __atomic_fetch_or(&B.surface, m, __ATOMIC_RELAXED);
        const int fc = faces_of[cfg];
        if (fc & 1) push(-1, 0, 0);
        if (fc & 2) push(1, 0, 0);
        if (fc & 4) push(0, -1, 0);
        if (fc & 8) push(0, 1, 0);
        if (fc & 16) push(0, 0, -1);
        if (fc & 32) push(0, 0, 1);
      });
      next.clear();
      for (auto& v : next_local) {
        next.insert(next.end(), v.begin(), v.end());
        v.clear();
      }
      // Steps into blocks not there yet (serial: the blocks are created).
      for (auto& v : deferred_local) {
        for (std::uint64_t d : v) {
          const std::uint64_t c = d >> 5;
          const int q = int(d & 31);
          const std::int32_t b = std::int32_t(c >> 6);
          const int l = int(c & 63);
          const auto [nb, nl] =
              nodes_.rel_get(b, (l & 3) + q % 3 - 1, (l >> 2 & 3) + q / 3 % 3 - 1, (l >> 4) + q / 9 - 1);
          if (visit(nb, nl, marked)) next.push_back(std::uint64_t(nb) << 6 | std::uint64_t(nl));
        }
        v.clear();
      }
      frontier.swap(next);
      first = false;
    }
    for (std::size_t n : evaluated_local) st_.evaluations += n;
    for (const auto& v : marked_local) marked.insert(marked.end(), v.begin(), v.end());
    for (std::int32_t b : marked) nodes_.blk(b).mark = 0;
  }
  // Claims cell l of block b for the walk (parallel): false when it is a crossed cell
  // already or visited; a block whose first mark bit this sets goes to `marked`.
  bool visit(std::int32_t b, int l, std::vector<std::int32_t>& marked) {
    Lattice::Block& B = nodes_.blk(b);
    const std::uint64_t m = std::uint64_t(1) << l;
    if ((__atomic_load_n(&B.surface, __ATOMIC_RELAXED) & m) || (__atomic_load_n(&B.mark, __ATOMIC_RELAXED) & m))
      return false;
    const std::uint64_t old = __atomic_fetch_or(&B.mark, m, __ATOMIC_RELAXED);
    if (old & m) return false;
    if (!old) marked.push_back(b);
    return true;
  }

  // After lattice points moved: only the cells having one as a corner can change; they
  // are re-examined and the walk continues from them into cells not yet known.
  void update_surface(const std::vector<Key>& moved) {
    std::vector<std::uint64_t> cells;  // block << 6 | local index (duplicates: traverse drops them)
    for (Key p : moved) {
      const std::int32_t b = nodes_.block_of(p);
      const int l = Lattice::local(p);
      for (int q = 0; q < 8; ++q) {
        const int dx = q & 1, dy = q >> 1 & 1, dz = q >> 2 & 1;
        if (!cell_in_grid(ki(p) - dx, kj(p) - dy, kk(p) - dz)) continue;
        const auto [cb, cl] = nodes_.rel_get(b, (l & 3) - dx, (l >> 2 & 3) - dy, (l >> 4) - dz);
        nodes_.blk(cb).surface &= ~(std::uint64_t(1) << cl);
        cells.push_back(std::uint64_t(cb) << 6 | std::uint64_t(cl));
      }
    }
    traverse(cells, false);
  }

  // ---------------------------------------------------------------- step 1
  // Samples Omega of lattice point p at step h/m; returns true and the new position and
  // value when samples of the wanted sign (inside when want_inside) exist: their
  // centroid, or, where the centroid itself has the wrong sign (a non-convex part), the
  // wanted sample nearest to it.
  bool search(Key p, bool want_inside, Vec3d& pos, double& value) const {
    const Vec3d c0 = upos(p);
    const double step = h_ / m_;
    Vec3d sum = Vec3d::Zero();
    int count = 0;
    thread_local std::vector<std::pair<Vec3d, double>> hits;
    hits.clear();
    // All m^3 samples at once: f may share work between them (values_near).
    thread_local std::vector<Vec3d> xs;
    thread_local std::vector<double> vs;
    xs.clear();
    for (int a = 0; a < m_; ++a)
      for (int b = 0; b < m_; ++b)
        for (int c = 0; c < m_; ++c)
          xs.push_back(c0 + Vec3d((a + 0.5) * step - 0.5 * h_, (b + 0.5) * step - 0.5 * h_,
                                  (c + 0.5) * step - 0.5 * h_));
    vs.resize(xs.size());
    f_.values_near(xs.data(), int(xs.size()), vs.data());
    for (std::size_t at = 0; at < xs.size(); ++at) {
      double v = vs[at] - opt_.iso;
      if (!std::isfinite(v)) v = h_;
      if ((v < 0) == want_inside) {
        sum += xs[at];
        ++count;
        hits.emplace_back(xs[at], v);
      }
    }
    if (count == 0) return false;
    pos = sum / count;
    double v = g(pos);
    if (!std::isfinite(v)) v = h_;
    if ((v < 0) != want_inside) {
      std::size_t best = 0;
      for (std::size_t i = 1; i < hits.size(); ++i)
        if ((hits[i].first - pos).squaredNorm() < (hits[best].first - pos).squaredNorm()) best = i;
      pos = hits[best].first;
      v = hits[best].second;
    }
    value = v;
    return true;
  }

  // The lattice value of p's neighbour `step` (+-1) along `axis` (p is point l of block
  // b), through the links: its node's, or its scan line's; false when it was never
  // evaluated or is outside the grid.
  bool neighbour_value(Key p, std::int32_t b, int l, int axis, int step, double& v) const {
    int d[3] = {ki(p), kj(p), kk(p)};
    d[axis] += step;
    if (!node_in_grid(d[0], d[1], d[2])) return false;
    int r[3] = {l & 3, l >> 2 & 3, l >> 4};
    r[axis] += step;
    const auto [nb, nl] = nodes_.rel(b, r[0], r[1], r[2]);
    if (nodes_.present(nb, nl)) {
      v = nodes_.node(nb, nl).val;
      return true;
    }
    if (const double* sv = scan_value(d[0], d[1], d[2])) {
      v = *sv;
      return true;
    }
    return false;
  }

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
  static bool cheap_candidate(const Node& nd, const Neighbours& nb, double h) {
    double slope = 0;
    for (int q = 0; q < 6; ++q) {
      if (!nb.has[q]) continue;
      slope = std::max(slope, std::abs(nb.v[q] - nd.val) / h);
    }
    return !(std::abs(nd.val) > 1.3 * h * slope * 1.5) || slope == 0;
  }

  // grad f at lattice point p from the lattice values alone: central differences with
  // its evaluated 6-neighbours (one-sided where one side is missing); false when an
  // axis has neither. Only before any point moved (the differences assume undeformed
  // neighbours): the first wave's probe direction.
  static constexpr double kLinear = 3, kTangent = 0.25;
  bool lattice_gradient(const Node& nd, const Neighbours& nb, Vec3d& gr) const {
    double dps[3], dms[3];
    bool both[3];
    for (int a = 0; a < 3; ++a) {
      const double vp = nb.has[2 * a + 1] ? nb.v[2 * a + 1] : 0, vm = nb.has[2 * a] ? nb.v[2 * a] : 0;
      const bool hp = nb.has[2 * a + 1], hm = nb.has[2 * a];
      both[a] = hp && hm;
      if (hp && hm) {
        dps[a] = vp - nd.val;
        dms[a] = nd.val - vm;
        gr[a] = 0.5 * (vp - vm) / h_;
      } else if (hp) {
        gr[a] = (vp - nd.val) / h_;
      } else if (hm) {
        gr[a] = (nd.val - vm) / h_;
      } else {
        return false;
      }
    }
    // f about linear along each axis that carries the gradient: both one-sided
    // differences of one sign, neither over kLinear times the other (a thin part or a
    // valley between the neighbours bends it; f's gradient decides there). An axis
    // whose differences are both under kTangent of the gradient's size per cell runs
    // along the surface: its component is small whatever its sign.
    const double g = gr.norm() * h_;
    for (int a = 0; a < 3; ++a) {
      if (!both[a]) continue;
      const double lo = std::min(std::abs(dps[a]), std::abs(dms[a])), hi = std::max(std::abs(dps[a]), std::abs(dms[a]));
      if (hi <= kTangent * g) continue;
      if (!(dps[a] * dms[a] > 0) || hi > kLinear * lo) return false;
    }
    return true;
  }

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
  bool probe(const Node& nd, char role) const {
    const Vec3d gr = f_.gradient(nd.pos);
    const double gn = gr.norm();
    if (!(gn > 0) || !std::isfinite(gn)) return role == kMove;  // no usable gradient: search
    const double d = std::abs(nd.val) / gn;
    if (d > 1.3 * h_) return false;
    if (role == kMove) return d <= omega_reach(gr / gn);
    const double sgn = nd.val < 0 ? -1.0 : 1.0;  // outside: towards -grad
    const Vec3d n = gr / gn;
    double v = g(Vec3d(nd.pos + sgn * h_ * n));
    if (!std::isfinite(v)) v = h_;
    return (v < 0) != (nd.val < 0);
  }

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
  void probe_round(ProbeBatch& batch, const std::vector<int>& at, std::vector<int>& thin) const {
    batch.probes.clear();
    batch.probe_of.assign(at.size(), -1);
    for (std::size_t t = 0; t < at.size(); ++t) {
      const std::size_t i = std::size_t(at[t]);
      const Node& nd = *batch.nodes[i];
      const Vec3d& gr = batch.grads[i];
      const double gn = gr.norm();
      if (!(gn > 0) || !std::isfinite(gn)) {  // no usable gradient: search
        thin.push_back(at[t]);
        continue;
      }
      const double d = std::abs(nd.val) / gn;
      if (d > 1.3 * h_) continue;
      const double sgn = nd.val < 0 ? -1.0 : 1.0;  // outside: towards -grad
      batch.probe_of[t] = int(batch.probes.size());
      batch.probes.push_back(nd.pos - sgn * (d + h_) * (gr / gn));  // one h past the near surface
    }
    if (batch.probes.empty()) return;
    batch.values.resize(batch.probes.size());
    f_.values_near(batch.probes.data(), int(batch.probes.size()), batch.values.data());
    for (std::size_t t = 0; t < at.size(); ++t) {
      if (batch.probe_of[t] < 0) continue;
      double v = batch.values[std::size_t(batch.probe_of[t])] - opt_.iso;
      if (!std::isfinite(v)) v = h_;
      if ((v < 0) == (batch.nodes[std::size_t(at[t])]->val < 0)) thin.push_back(at[t]);
    }
  }
  // Counts: probes taken, f's gradients taken.
  void probe_first_wave(ProbeBatch& batch, std::vector<Key>& todo, std::size_t& probes, std::size_t& gradients) const {
    const std::size_t n = batch.nodes.size();
    if (n == 0) return;
    std::vector<int>&lattice = batch.lattice, &exact = batch.exact, &thin = batch.thin;
    lattice.clear();
    exact.clear();
    thin.clear();
    for (std::size_t i = 0; i < n; ++i) (batch.has_grad[i] ? lattice : exact).push_back(int(i));
    probe_round(batch, lattice, exact);
    probes += batch.probes.size();
    if (exact.empty()) return;
    std::sort(exact.begin(), exact.end());
    batch.xs.resize(exact.size());
    batch.exact_grads.resize(exact.size());
    for (std::size_t t = 0; t < exact.size(); ++t) batch.xs[t] = batch.nodes[std::size_t(exact[t])]->pos;
    f_.gradients_near(batch.xs.data(), int(exact.size()), batch.exact_grads.data());
    for (std::size_t t = 0; t < exact.size(); ++t) batch.grads[std::size_t(exact[t])] = batch.exact_grads[t];
    gradients += exact.size();
    probe_round(batch, exact, thin);
    probes += batch.probes.size();
    for (int i : thin) todo.push_back(batch.keys[std::size_t(i)]);
  }

  // The first wave of the flood, in parallel over the blocks: the corners of the crossed
  // cells, each once (mark bits claimed atomically, cleared after), pre-tested and
  // probed a block at a time; the points whose Omega is to be searched, in key order.
  std::vector<Key> first_wave_todo() {
    tbb::enumerable_thread_specific<std::vector<Key>> todo_local;
    tbb::enumerable_thread_specific<std::vector<std::int32_t>> marked_local;
    tbb::enumerable_thread_specific<std::size_t> probed_local(0), exact_local(0), probes_local(0);
    tbb::enumerable_thread_specific<ProbeBatch> batch_local;
    parallel(nodes_.block_count(), [&](std::size_t bs) {
      const std::int32_t b = std::int32_t(bs);
      ProbeBatch& batch = batch_local.local();
      batch.clear();
      for (std::uint64_t m = nodes_.blk(b).surface; m; m &= m - 1) {
        const int l = __builtin_ctzll(m), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
        for (int q = 0; q < 8; ++q) {
          const auto [cb, cl] = nodes_.rel(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
          Lattice::Block& B = nodes_.blk(cb);
          const std::uint64_t bit = std::uint64_t(1) << cl;
          if (__atomic_load_n(&B.mark, __ATOMIC_RELAXED) & bit) continue;
          const std::uint64_t old = __atomic_fetch_or(&B.mark, bit, __ATOMIC_RELAXED);
          if (old & bit) continue;
          if (!old) marked_local.local().push_back(cb);
          Node& nd = nodes_.node(cb, cl);
          if (nd.flags & kFixed) continue;
          // Outside points move into thin parts, inside points into thin gaps.
          if (nd.val < 0 ? !opt_.thin_gaps : !opt_.barycentre) continue;
          const Key p = nodes_.point(cb, cl);
          Neighbours nb;
          neighbour_values(p, cb, cl, nb);
          if (cheap_candidate(nd, nb, h_)) {
            ++probed_local.local();
            batch.nodes.push_back(&nd);
            batch.keys.push_back(p);
            batch.grads.emplace_back();
            batch.has_grad.push_back(lattice_gradient(nd, nb, batch.grads.back()));
          }
          nd.flags |= kSearched;
        }
      }
      probe_first_wave(batch, todo_local.local(), probes_local.local(), exact_local.local());
    });
    std::size_t probed = 0;
    for (std::size_t n : probed_local) probed += n;
    for (std::size_t n : exact_local) st_.gradient_evaluations += n;
    for (std::size_t n : probes_local) st_.evaluations += n;
    st_.probed += probed;
    for (const auto& v : marked_local)
      for (std::int32_t b : v) nodes_.blk(b).mark = 0;
    std::vector<Key> todo;
    for (const auto& v : todo_local) todo.insert(todo.end(), v.begin(), v.end());
    std::sort(todo.begin(), todo.end());
    return todo;
  }

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
  std::vector<Key> barycentre_step() {
    std::vector<Key> cand;
    std::vector<std::uint32_t> cand_h;  // block << 6 | local index of each candidate
    std::vector<Key> moved_all;
    bool first_wave = true;
    // Which flood reached each candidate: 1 thin part (inside), 2 thin gap (outside).
    std::vector<std::uint8_t> cand_by;
    while (first_wave || !cand.empty()) {
      std::vector<Key> todo, through;
      if (first_wave) {
        todo = first_wave_todo();
      } else {
        std::vector<Key> keep;
        std::vector<Node*> keep_node;
        std::vector<char> role;
        // Which floods each candidate takes on (bit kind) and as what (bit kind << 2:
        // mover), in parallel: a wave's candidates are distinct points, so each
        // iteration reads and marks its own node only. Then kept in candidate order.
        std::vector<std::uint8_t> take(cand.size(), 0);
        std::vector<Node*> cand_node(cand.size());
        parallel(cand.size(), [&](std::size_t ci) {
          Node& nd = nodes_.node(std::int32_t(cand_h[ci] >> 6), int(cand_h[ci] & 63));
          cand_node[ci] = &nd;
          if (nd.flags & kFixed) return;
          const bool inside = nd.val < 0;
          const std::uint8_t by = cand_by[ci];
          std::uint8_t t = 0;
          for (std::uint8_t kind = 1; kind <= 2; ++kind) {
            if (!(by & kind)) continue;
            if (kind == 1 ? !opt_.barycentre : !opt_.thin_gaps) continue;
            // Moves: outside points into thin parts, inside points into thin gaps.
            const bool mover = (kind == 1) != inside;
            const std::uint8_t passed = kind == 1 ? kPassedPart : kPassedGap;
            if (mover ? (nd.flags & kSearched) != 0 : (nd.flags & passed) != 0) continue;
            if (!mover) nd.flags |= passed;
            t |= std::uint8_t(kind | (mover ? kind << 2 : 0));
          }
          take[ci] = t;
        });
        for (std::size_t ci = 0; ci < cand.size(); ++ci)
          for (std::uint8_t kind = 1; kind <= 2; ++kind) {
            if (!(take[ci] & kind)) continue;
            keep.push_back(cand[ci]);
            keep_node.push_back(cand_node[ci]);
            role.push_back(take[ci] & (kind << 2) ? kMove : kPass);
          }
        // Gradient test and thin probe, in parallel.
        std::vector<char> go(keep.size(), 0);
        parallel(keep.size(), [&](std::size_t i) { go[i] = probe(*keep_node[i], role[i]); });
        st_.gradient_evaluations += keep.size();
        for (std::size_t i = 0; i < keep.size(); ++i)
          if (role[i] == kPass) ++st_.probed, ++st_.evaluations;
        for (std::size_t i = 0; i < keep.size(); ++i)
          if (go[i]) (role[i] == kMove ? todo : through).push_back(keep[i]);
        for (std::size_t i = 0; i < keep.size(); ++i)
          if (role[i] == kMove) keep_node[i]->flags |= kSearched;
      }
      std::vector<char> ok(todo.size(), 0);
      std::vector<Vec3d> pos(todo.size());
      std::vector<double> value(todo.size());
      parallel(todo.size(), [&](std::size_t i) {
        ok[i] = search(todo[i], !(nodes_.at(todo[i]).val < 0), pos[i], value[i]);
      });
      st_.searched += todo.size();
      st_.evaluations += todo.size() * (std::size_t(m_) * m_ * m_);
      std::vector<std::pair<Key, std::uint8_t>> spread;  // (point, flood kind)
      for (std::size_t i = 0; i < todo.size(); ++i) {
        if (!ok[i]) continue;
        Node& nd = nodes_.at(todo[i]);
        st_.evaluations += 1;
        const bool was_inside = nd.val < 0;
        original_.emplace(todo[i], nd.val);
        nd.pos = pos[i];
        nd.val = value[i];
        nd.flags |= was_inside ? kGap : kBary;
        ++(was_inside ? st_.moved_gap : st_.moved_barycentre);
        moved_all.push_back(todo[i]);
        spread.emplace_back(todo[i], was_inside ? 2 : 1);
      }
      for (Key p : through) spread.emplace_back(p, nodes_.at(p).val < 0 ? 1 : 2);
      // Next wave: the 26 neighbours, each once, with the floods that reached it (mark
      // bits for the thin part's flood, mark2 for the thin gap's); the new points are
      // entered and evaluated. Marked in parallel (bits set atomically; a block is listed
      // by the caller that set the first bit of one of its masks); the neighbours in
      // blocks that do not exist yet (few: the walk made the blocks around the surface)
      // are marked after, serially, their blocks created. The touched blocks are then
      // taken in block order, so the candidates' order does not depend on the threads
      // (nothing below depends on it: each candidate reads and writes its own node).
      auto mark = [&](std::int32_t nb, int nl, std::uint8_t kind, std::vector<std::int32_t>& touched_out) {
        Lattice::Block& B = nodes_.blk(nb);
        const std::uint64_t bit = std::uint64_t(1) << nl;
        if (!(__atomic_fetch_or(kind == 1 ? &B.mark : &B.mark2, bit, __ATOMIC_RELAXED))) touched_out.push_back(nb);
      };
      tbb::enumerable_thread_specific<std::vector<std::int32_t>> touched_local;
      tbb::enumerable_thread_specific<std::vector<std::pair<std::size_t, int>>> missing_local;  // (spread item, q)
      parallel(spread.size(), [&](std::size_t si) {
        const auto [p, kind] = spread[si];
        const std::int32_t b = nodes_.block_of(p);
        const int l = Lattice::local(p);
        std::vector<std::int32_t>& touched_here = touched_local.local();
        for (int q = 0; q < 27; ++q) {
          const int dx = q % 3 - 1, dy = q / 3 % 3 - 1, dz = q / 9 - 1;
          if (q == 13 || !node_in_grid(ki(p) + dx, kj(p) + dy, kk(p) + dz)) continue;
          const auto [nb, nl] = nodes_.rel(b, (l & 3) + dx, (l >> 2 & 3) + dy, (l >> 4) + dz);
          if (nb < 0) {
            missing_local.local().emplace_back(si, q);
            continue;
          }
          mark(nb, nl, kind, touched_here);
        }
      });
      std::vector<std::int32_t> touched;
      for (const auto& v : touched_local) touched.insert(touched.end(), v.begin(), v.end());
      std::vector<std::pair<std::size_t, int>> missing;  // in spread order: blocks made as in one serial pass
      for (const auto& v : missing_local) missing.insert(missing.end(), v.begin(), v.end());
      std::sort(missing.begin(), missing.end());
      for (const auto& [si, q] : missing) {
        const auto [p, kind] = spread[si];
        const int l = Lattice::local(p);
        const auto [nb, nl] = nodes_.rel_get(nodes_.block_of(p), (l & 3) + q % 3 - 1, (l >> 2 & 3) + q / 3 % 3 - 1,
                                             (l >> 4) + q / 9 - 1);
        mark(nb, nl, kind, touched);
      }
      std::sort(touched.begin(), touched.end());
      touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
      cand.clear();
      cand_h.clear();
      cand_by.clear();
      std::vector<std::uint32_t> fresh;
      for (std::int32_t b : touched) {
        Lattice::Block& B = nodes_.blk(b);
        for (std::uint64_t m = B.mark | B.mark2; m; m &= m - 1) {
          const int l = __builtin_ctzll(m);
          const Key k = nodes_.point(b, l);
          cand.push_back(k);
          cand_h.push_back(std::uint32_t(b) << 6 | std::uint32_t(l));
          cand_by.push_back(std::uint8_t((B.mark >> l & 1) | (B.mark2 >> l & 1) << 1));
          if (nodes_.enter(b, l, Node{upos(k), 0.0, std::uint8_t(on_boundary(k) ? kFixed : 0)}))
            fresh.push_back(std::uint32_t(b) << 6 | std::uint32_t(l));
        }
        B.mark = B.mark2 = 0;
      }
      evaluate(fresh);
      first_wave = false;
    }
    bridge(moved_all);
    prune_islands(moved_all);
    return moved_all;
  }

  // Moved points that are neighbours only across a cell edge or corner would stay apart
  // in MC (ambiguous faces keep inside corners apart): where the segment between them
  // lies in the part (gap), the lattice points whose Omega it crosses move onto it.
  void bridge(std::vector<Key>& moved) {
    std::sort(moved.begin(), moved.end());
    // In parallel over runs of `moved`; the runs' proposals joined in order (the same
    // list as one serial pass). Below, among proposals for one key, the one std::sort
    // leaves first is taken: not the first in this list (the sort is not stable), but
    // the same for the same list, so the same for any thread count.
    constexpr std::size_t kRun = 256;
    std::vector<std::vector<std::pair<Key, Vec3d>>> run_props((moved.size() + kRun - 1) / kRun);
    parallel(run_props.size(), [&](std::size_t ri) {
      std::vector<std::pair<Key, Vec3d>>& props = run_props[ri];
      for (std::size_t mi = ri * kRun; mi < std::min(moved.size(), (ri + 1) * kRun); ++mi) {
        const Key p = moved[mi];
        const Node& a = nodes_.at(p);
        const std::uint8_t kind = a.flags & (kBary | kGap);
        for (int q = 0; q < 27; ++q) {
          const int dx = q % 3 - 1, dy = q / 3 % 3 - 1, dz = q / 9 - 1;
          if (std::abs(dx) + std::abs(dy) + std::abs(dz) < 2) continue;
          if (!node_in_grid(ki(p) + dx, kj(p) + dy, kk(p) + dz)) continue;
          const Key r = key(ki(p) + dx, kj(p) + dy, kk(p) + dz);
          if (r < p) continue;
          const auto it = nodes_.find(r);
          if (it == nullptr || (it->flags & (kBary | kGap)) != kind) continue;
          const Vec3d x0 = a.pos, x1 = it->pos;
          // Omegas along the segment, each with the middle of its piece.
          Key last = p;
          double t_in = 0;
          constexpr int kSteps = 32;
          for (int st = 1; st <= kSteps; ++st) {
            const double t = double(st) / kSteps;
            const Vec3d y = ((x0 + t * (x1 - x0)) - lo_) / h_;
            const Key cur = key(round_coordinate(y.x()), round_coordinate(y.y()), round_coordinate(y.z()));
            if (cur == last) continue;
            if (last != p) props.emplace_back(last, x0 + 0.5 * (t_in + t - 1.0 / kSteps) * (x1 - x0));
            last = cur;
            t_in = t;
          }
        }
      }
    });
    std::vector<std::pair<Key, Vec3d>> props;
    for (const auto& v : run_props) props.insert(props.end(), v.begin(), v.end());
    run_props.clear();
    std::sort(props.begin(), props.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    props.erase(std::unique(props.begin(), props.end(), [](const auto& a, const auto& b) { return a.first == b.first; }),
                props.end());
    std::vector<Key> keys;
    for (const auto& pr : props) keys.push_back(pr.first);
    ensure(keys);
    std::vector<std::pair<Key, Vec3d>> apply;
    for (const auto& pr : props) {
      const Node& nd = nodes_.at(pr.first);
      if (nd.flags & (kFixed | kBary | kGap)) continue;
      const Vec3d cen = upos(pr.first);
      if (((pr.second - cen).array().abs() > 0.5 * h_).any()) continue;
      apply.push_back(pr);
    }
    std::vector<double> v(apply.size());
    parallel(apply.size(), [&](std::size_t i) {
      const double x = g(apply[i].second);
      v[i] = std::isfinite(x) ? x : h_;
    });
    st_.evaluations += apply.size();
    // Bridges only where the lattice point changes side (and lands in the part).
    std::size_t added = 0;
    for (std::size_t i = 0; i < apply.size(); ++i) {
      Node& nd = nodes_.at(apply[i].first);
      if ((nd.val < 0) == (v[i] < 0)) continue;
      const bool was_inside = nd.val < 0;
      original_.emplace(apply[i].first, nd.val);
      nd.pos = apply[i].second;
      nd.val = v[i];
      nd.flags |= kSearched | (was_inside ? kGap : kBary);
      ++(was_inside ? st_.moved_gap : st_.moved_barycentre);
      moved.push_back(apply[i].first);
      ++added;
    }
    st_.bridged = added;
  }

  // A few moved points that touch no unmoved point of their new sign (6-neighbours)
  // would be a speck of their own: slivers of a convex edge or corner cut off by an
  // Omega, not a thin part (which floods into many points). They move back.
  void prune_islands(std::vector<Key>& moved) {
    constexpr std::size_t kMinIsland = 4;
    std::sort(moved.begin(), moved.end());
    // Each point on its own, in parallel: a walk over its group (moved points of its
    // kind, 6-connected) that stops once the group has kMinIsland points or touches an
    // unmoved point of the new side. A walk that runs out first has seen its whole group,
    // small and unanchored: the point moves back. The same points as walking each group
    // once (a point is in `moved` exactly when its node carries kBary or kGap).
    std::vector<char> back(moved.size(), 0);
    parallel(moved.size(), [&](std::size_t si) {
      const Key s = moved[si];
      const std::uint8_t kind = nodes_.at(s).flags & (kBary | kGap);
      Key group[kMinIsland];
      std::size_t n = 1, next = 0;
      group[0] = s;
      Node tmp;
      while (next < n) {
        const Key p = group[next++];
        for (int q = 0; q < 6; ++q) {
          int d[3] = {ki(p), kj(p), kk(p)};
          d[q / 2] += q % 2 ? 1 : -1;
          if (!node_in_grid(d[0], d[1], d[2])) continue;
          const Key r = key(d[0], d[1], d[2]);
          const Node* it = known(r, tmp);
          if (it == nullptr) continue;
          if (it->flags & (kBary | kGap)) {
            if ((it->flags & (kBary | kGap)) != kind || std::find(group, group + n, r) != group + n) continue;
            if (n + 1 == kMinIsland) return;  // a group this large is a thin part
            group[n++] = r;
          } else if ((it->val < 0) == (kind == kBary)) {
            return;  // anchored
          }
        }
      }
      back[si] = 1;
    });
    std::vector<Key> revert;
    for (std::size_t si = 0; si < moved.size(); ++si)
      if (back[si]) revert.push_back(moved[si]);
    for (Key p : revert) {
      Node& nd = nodes_.at(p);
      --(nd.flags & kGap ? st_.moved_gap : st_.moved_barycentre);
      nd.flags &= std::uint8_t(~(kBary | kGap));
      nd.pos = upos(p);
      nd.val = original_.at(p);
    }
    st_.reverted = revert.size();
    moved.erase(std::remove_if(moved.begin(), moved.end(), [&](Key p) { return !(nodes_.at(p).flags & (kBary | kGap)); }),
                moved.end());
  }

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
                 Crossing* out) const {
    if (n <= 0) return 0;
    std::size_t gradients = 0;
    cb.state.resize(std::size_t(n));
    cb.grads.resize(std::size_t(n));
    for (int i = 0; i < n; ++i) {
      const double fa = a[i]->val, fb = b[i]->val;
      cb.state[std::size_t(i)] = {fa, fb, 0.0, 1.0, fa / (fa - fb), 1e-7 * std::abs(fa - fb), 0, 0, false};
    }
    for (int it = 0; it < steps; ++it) {
      cb.active.clear();
      cb.xs.clear();
      for (int i = 0; i < n; ++i) {
        const auto& st = cb.state[std::size_t(i)];
        if (st.done) continue;
        cb.active.push_back(i);
        cb.xs.push_back(a[i]->pos + st.t * (b[i]->pos - a[i]->pos));
      }
      if (cb.active.empty()) break;
      cb.values.resize(cb.xs.size());
      cb.last_grads.resize(cb.xs.size());
      f_.values_gradients_near(cb.xs.data(), int(cb.xs.size()), cb.values.data(), cb.last_grads.data());
      gradients += cb.xs.size();
      for (std::size_t k = 0; k < cb.active.size(); ++k) {
        const int i = cb.active[k];
        auto& st = cb.state[std::size_t(i)];
        const Vec3d& gr = cb.last_grads[k];
        cb.grads[std::size_t(i)] = gr;
        const double v = cb.values[k] - opt_.iso;
        ++st.evals;
        if (!std::isfinite(v) || std::abs(v) <= st.tol) {
          st.done = true;
          continue;
        }
        if ((v < 0) == (a[i]->val < 0)) {
          st.lo = st.t;
          st.fa = v;
          if (st.side == -1) st.fb *= 0.5;
          st.side = -1;
        } else {
          st.hi = st.t;
          st.fb = v;
          if (st.side == 1) st.fa *= 0.5;
          st.side = 1;
        }
        // Newton along the edge (f's derivative along it from the gradient), kept
        // inside the bracket; else the Illinois step.
        const double slope = gr.dot(b[i]->pos - a[i]->pos);
        const double tn = st.t - v / slope;
        // The Newton step's error, (q'' / 2 q') dt^2 for q = f along the edge, q''
        // from how far the secants to the edge's ends stray from the tangent (a kink
        // shows as a large q''): below done_error (fraction of the edge) the crossing
        // is done; above kNewtonTrust the quadratic model is not trusted and the
        // Illinois step is taken.
        double est = std::numeric_limits<double>::infinity();
        if (tn > st.lo && tn < st.hi) {
          const double t0 = st.t, fa0 = a[i]->val, fb0 = b[i]->val;
          double curv = 0;
          if (t0 > 1e-3) curv = std::max(curv, std::abs(2 * (slope - (v - fa0) / t0) / t0));
          if (t0 < 1 - 1e-3) curv = std::max(curv, std::abs(2 * ((fb0 - v) / (1 - t0) - slope) / (1 - t0)));
          est = curv / (2 * std::abs(slope)) * (tn - t0) * (tn - t0);
        }
        const double t_before = st.t;
        if (est <= kNewtonTrust) {
          st.t = tn;
          if (est <= done_error) st.done = true;
        } else {
          st.t = st.lo + (st.hi - st.lo) * st.fa / (st.fa - st.fb);
          if (!(st.t >= st.lo && st.t <= st.hi)) st.t = 0.5 * (st.lo + st.hi);
        }
        // Located to kLocated of the edge (the step or the bracket): done, even where
        // f's own round-off (a blend, a far-field sum) keeps |f| above tol.
        if (std::abs(st.t - t_before) <= kLocated || st.hi - st.lo <= kLocated) st.done = true;
      }
    }
    cb.xs.resize(std::size_t(n));
    for (int i = 0; i < n; ++i) {
      // Kept off the lattice points so no triangle collapses.
      const double t = std::clamp(cb.state[std::size_t(i)].t, 1e-3, 1 - 1e-3);
      cb.xs[std::size_t(i)] = a[i]->pos + t * (b[i]->pos - a[i]->pos);
    }
    // Gradients at the crossings of the edges never evaluated (each evaluation took
    // one), together.
    cb.active.clear();
    for (int i = 0; i < n; ++i)
      if (cb.state[std::size_t(i)].evals == 0) cb.active.push_back(i);
    if (!cb.active.empty()) {
      cb.at.resize(cb.active.size());
      cb.last_grads.resize(cb.active.size());
      for (std::size_t k = 0; k < cb.active.size(); ++k) cb.at[k] = cb.xs[std::size_t(cb.active[k])];
      f_.gradients_near(cb.at.data(), int(cb.at.size()), cb.last_grads.data());
      for (std::size_t k = 0; k < cb.active.size(); ++k) cb.grads[std::size_t(cb.active[k])] = cb.last_grads[k];
      gradients += cb.active.size();
    }
    for (int i = 0; i < n; ++i) {
      Crossing& c = out[i];
      c = Crossing{};
      c.evals = cb.state[std::size_t(i)].evals;
      c.pos = cb.xs[std::size_t(i)];
      const Vec3d& gr = cb.grads[std::size_t(i)];
      const double len = gr.norm();
      c.normal = len > 0 && std::isfinite(len) ? Vec3d(gr / len) : Vec3d::Zero();
    }
    return gradients;
  }

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
  static constexpr double kLocated = 1e-9;      // a crossing this close (of the edge) is done
  std::size_t solve(EdgeBatch& eb, int steps, double done_error, std::size_t& gradients) const {
    const int n = int(eb.out.size());
    eb.result.resize(std::size_t(n));
    gradients += crossings(eb.a.data(), eb.b.data(), n, steps, done_error, eb.work, eb.result.data());
    std::size_t evals = 0;
    for (int i = 0; i < n; ++i) {
      *eb.out[std::size_t(i)] = eb.result[std::size_t(i)];
      evals += std::size_t(eb.result[std::size_t(i)].evals);
    }
    return evals;
  }

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
  void want_crossings(std::int32_t b, int l) {
    const auto& ec = mc::edge_corners();
    const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
    const int cfg = config(b, l);
    for (int e = 0; e < 12; ++e) {
      if (!crossed(cfg, e)) continue;
      const int c0 = ec[e][0];
      const auto [cb, cl] = nodes_.rel(b, li + (c0 & 1), lj + (c0 >> 1 & 1), lk + (c0 >> 2 & 1));
      Lattice::set_bit(nodes_.blk(cb).xwant[e / 4], cl);
    }
  }

  void compute_crossings() {
    parallel(nodes_.block_count(), [&](std::size_t bs) {
      const std::int32_t b = std::int32_t(bs);
      for (std::uint64_t m = nodes_.blk(b).surface; m; m &= m - 1) want_crossings(b, __builtin_ctzll(m));
    });
    std::size_t wanted = 0;
    for (std::size_t bs = 0; bs < nodes_.block_count(); ++bs) {
      const Lattice::Block& B = nodes_.blk(std::int32_t(bs));
      const int n = detail::popcount64(B.xwant[0]) + detail::popcount64(B.xwant[1]) + detail::popcount64(B.xwant[2]);
      if (n == 0) continue;
      nodes_.make_slots(std::int32_t(bs));
      wanted += std::size_t(n);
    }
    nodes_.reserve_crossings(wanted);
    tbb::enumerable_thread_specific<std::size_t> evals_local(0), grads_local(0);
    tbb::enumerable_thread_specific<EdgeBatch> batch_local;
    parallel(nodes_.block_count(), [&](std::size_t bs) {
      const std::int32_t b = std::int32_t(bs);
      Lattice::Block& B = nodes_.blk(b);
      EdgeBatch& eb = batch_local.local();
      eb.clear();
      for (int a = 0; a < 3; ++a) {
        for (std::uint64_t m = B.xwant[a]; m; m &= m - 1) {
          const int l = __builtin_ctzll(m);
          std::uint32_t& slot = nodes_.slot(b, l, a);
          if (slot != Lattice::kNoCrossing && !nodes_.crossing_at(slot).stale) continue;
          if (slot == Lattice::kNoCrossing) slot = nodes_.claim_crossing();
          const auto [db, dl] = nodes_.rel(b, (l & 3) + (a == 0), (l >> 2 & 3) + (a == 1), (l >> 4) + (a == 2));
          eb.add(&nodes_.node(b, l), &nodes_.node(db, dl), &nodes_.crossing_at(slot));
        }
        B.xwant[a] = 0;
      }
      evals_local.local() += solve(eb, opt_.refine_steps, kNewtonDone, grads_local.local());
    });
    for (std::size_t n : grads_local) st_.gradient_evaluations += n;
    for (std::size_t n : evals_local) st_.evaluations += n;
  }

  // ---------------------------------------------------------------- step 2
  // Per crossed cell: sharp edge / corner from the crossing normals; proposals for the
  // lattice points to move.
  // Run twice (feature_step): first (refined false) it only tells whether the cell's
  // crossings suggest a feature (then they are refined to round-off, each edge once, and
  // kept in Crossing::refined); then, for those cells, it finds the feature.
  bool detect(Key c, std::vector<Proposal>& out, bool refined) const {
    const auto& ec = mc::edge_corners();
    Vec3d pts[12], nrm[12];
    const Crossing* xs[12];
    int n = 0;
    const std::int32_t cb = nodes_.block_of(c);
    const int cl = Lattice::local(c), cli = cl & 3, clj = cl >> 2 & 3, clk = cl >> 4;
    const Node* corner_node[8];
    for (int q = 0; q < 8; ++q) {
      const auto [qb, ql] = nodes_.rel(cb, cli + (q & 1), clj + (q >> 1 & 1), clk + (q >> 2 & 1));
      corner_node[q] = &nodes_.node(qb, ql);
    }
    int cfg = 0;
    for (int q = 0; q < 8; ++q)
      if (corner_node[q]->val < 0) cfg |= 1 << q;
    for (int e = 0; e < 12; ++e) {
      if (!crossed(cfg, e)) continue;
      const int c0 = ec[e][0];
      const auto [xb, xl] = nodes_.rel(cb, cli + (c0 & 1), clj + (c0 >> 1 & 1), clk + (c0 >> 2 & 1));
      const Crossing* xp = nodes_.crossing(xb, xl, e / 4);
      if (!xp) throw std::out_of_range("extract_dmc: internal error: crossing not computed");
      const Crossing& x = *xp;
      if (x.normal.squaredNorm() == 0) return false;  // no usable normal: leave the cell alone
      xs[n] = xp;
      pts[n] = x.pos;
      nrm[n] = x.normal;
      ++n;
    }
    if (n < 3) return false;
    // The pair of normals farthest apart that are not (anti)parallel: a thin sheet's two
    // sides face opposite ways but make no edge.
    double theta = 1;
    int a0 = -1, a1 = -1;
    for (int i = 0; i < n; ++i)
      for (int j = i + 1; j < n; ++j) {
        const double d = nrm[i].dot(nrm[j]);
        if (d < theta && nrm[i].cross(nrm[j]).norm() > 0.1) theta = d, a0 = i, a1 = j;
      }
    if (a0 < 0 || theta >= opt_.theta_sharp) return false;
    if (!refined && opt_.features_where_sharp) {
      // Where f has no crease (an MPU surface away from its edge and corner fits), the
      // normals turning within the cell are a bend of the smooth surface, not an edge.
      Vec3d mid = Vec3d::Zero();
      for (int i = 0; i < n; ++i) mid += pts[i];
      if (!f_.may_be_sharp(mid / n, h_ * std::sqrt(3.0))) {
        smooth_cells_.fetch_add(1, std::memory_order_relaxed);
        return false;
      }
    }
    // A feature is likely: the planes need crossings on the surface to round-off, not
    // to the few refinement steps of the mesh vertices.
    if (!refined) return true;
    {
      for (int i = 0; i < n; ++i) {
        if (xs[i]->refined < 0) throw std::out_of_range("extract_dmc: internal error: crossing not refined");
        const Crossing& x = nodes_.refined(xs[i]->refined);
        if (x.normal.squaredNorm() == 0) return false;
        pts[i] = x.pos;
        nrm[i] = x.normal;
      }
      theta = 1;
      a0 = a1 = -1;
      for (int i = 0; i < n; ++i)
        for (int j = i + 1; j < n; ++j) {
          const double d = nrm[i].dot(nrm[j]);
          if (d < theta && nrm[i].cross(nrm[j]).norm() > 0.1) theta = d, a0 = i, a1 = j;
        }
      if (a0 < 0 || theta >= opt_.theta_sharp) return false;
    }
    const Vec3d ne = nrm[a0].cross(nrm[a1]).normalized();
    double phi = 0;
    for (int i = 0; i < n; ++i)
      if (i != a0 && i != a1) phi = std::max(phi, std::abs(nrm[i].dot(ne)));
    bool corner = phi > opt_.phi_corner;
    // Quadric of the tangent planes, minimised around the mass point with small
    // eigenvalues truncated (dual contouring's QEF): robust to near-parallel planes.
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Vec3d b = Vec3d::Zero(), mass = Vec3d::Zero();
    Vec3d nsum = Vec3d::Zero();
    for (int i = 0; i < n; ++i) {
      A += nrm[i] * nrm[i].transpose();
      b += nrm[i] * nrm[i].dot(pts[i]);
      mass += pts[i];
      nsum += nrm[i];
    }
    mass /= n;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(A);
    const Vec3d ev = es.eigenvalues();  // ascending
    const Eigen::Matrix3d V = es.eigenvectors();
    const double tol = 0.1 * ev[2];
    if (corner && ev[0] < tol) corner = false;  // only two independent planes: an edge
    const Vec3d r = b - A * mass;
    Vec3d x = mass;
    for (int k = corner ? 0 : 1; k < 3; ++k)
      if (ev[k] >= tol) x += V.col(k) * (V.col(k).dot(r) / ev[k]);
    if (!x.allFinite()) return true;
    const int ci = ki(c), cj = kj(c), ck = kk(c);
    // Tiny step into (or out of) the solid so the moved point keeps a clear sign.
    const Vec3d inward = -(corner ? nsum : Vec3d(nrm[a0] + nrm[a1])).normalized() * (2e-4 * h_);
    // Each corner of the cell whose Omega the half line x + t dir (t >= tmin) crosses
    // moves to the middle of that crossing.
    auto along = [&](const Vec3d& dir, double tmin, const Vec3d& nudge) {
      for (int qc = 0; qc < 8; ++qc) {
        const Key p = corner_key(c, qc);
        const Vec3d cen = upos(p);
        double t0 = tmin, t1 = 1e300;
        bool hit = true;
        for (int a = 0; a < 3 && hit; ++a) {
          const double lo = cen[a] - 0.5 * h_, hi = cen[a] + 0.5 * h_;
          if (std::abs(dir[a]) < 1e-12) {
            if (x[a] < lo || x[a] >= hi) hit = false;
            continue;
          }
          double u0 = (lo - x[a]) / dir[a], u1 = (hi - x[a]) / dir[a];
          if (u0 > u1) std::swap(u0, u1);
          t0 = std::max(t0, u0);
          t1 = std::min(t1, u1);
        }
        // Even a short clip counts: a skipped Omega would leave the chain of lattice
        // points along the edge only edge-connected.
        if (!hit || t1 - t0 < 1e-6 * h_) continue;
        out.push_back({p, 0, c, x + dir * (0.5 * (t0 + t1)), nudge, t1 - t0});
      }
    };
    if (corner) {
      const Vec3d q = (x - lo_) / h_;
      const int r0 = int(std::lround(q.x())), r1 = int(std::lround(q.y())), r2 = int(std::lround(q.z()));
      if (r0 < ci - 1 || r0 > ci + 2 || r1 < cj - 1 || r1 > cj + 2 || r2 < ck - 1 || r2 > ck + 2) return true;
      if (!node_in_grid(r0, r1, r2)) return true;
      out.push_back({key(r0, r1, r2), 1, c, x, inward, 0.0});
      // The three edges leaving the corner (between each pair of the three planes, on
      // the solid side of the third), so the corner's neighbours join it to the edges.
      int a2 = -1;
      double best = -1;
      for (int i = 0; i < n; ++i)
        if (i != a0 && i != a1 && std::abs(nrm[i].dot(ne)) > best) best = std::abs(nrm[i].dot(ne)), a2 = i;
      const Vec3d pl[3] = {nrm[a0], nrm[a1], nrm[a2]};
      for (int e = 0; e < 3; ++e) {
        const Vec3d& u = pl[(e + 1) % 3];
        const Vec3d& w = pl[(e + 2) % 3];
        Vec3d dir = u.cross(w);
        if (dir.norm() < 0.1) continue;
        dir.normalize();
        if (dir.dot(pl[e]) > 0) dir = -dir;
        along(dir, 0.0, -(u + w).normalized() * (2e-4 * h_));
      }
      return true;
    }
    // Edge: the line through x along the smallest eigenvector.
    along(V.col(0), -1e300, inward);
    return true;
  }

  // The crossings of the cells that suggest a feature, refined to round-off (up to 60
  // steps), each edge once (a crossing is shared by up to four cells): marked by the
  // cells in the block of the edge's lower end (xwant bits), computed per block in
  // parallel.
  void refine_sharp(const std::vector<Key>& cells, const std::vector<char>& sharp) {
    parallel(cells.size(), [&](std::size_t i) {
      if (sharp[i]) want_crossings(nodes_.block_of(cells[i]), Lattice::local(cells[i]));
    });
    std::size_t wanted = 0;
    for (std::size_t bs = 0; bs < nodes_.block_count(); ++bs) {
      const Lattice::Block& B = nodes_.blk(std::int32_t(bs));
      wanted += std::size_t(detail::popcount64(B.xwant[0]) + detail::popcount64(B.xwant[1]) +
                            detail::popcount64(B.xwant[2]));
    }
    nodes_.reserve_refined(wanted);
    tbb::enumerable_thread_specific<std::size_t> evals_local(0), grads_local(0);
    tbb::enumerable_thread_specific<EdgeBatch> batch_local;
    parallel(nodes_.block_count(), [&](std::size_t bs) {
      const std::int32_t b = std::int32_t(bs);
      Lattice::Block& B = nodes_.blk(b);
      EdgeBatch& eb = batch_local.local();
      eb.clear();
      for (int a = 0; a < 3; ++a) {
        for (std::uint64_t m = B.xwant[a]; m; m &= m - 1) {
          const int l = __builtin_ctzll(m);
          Crossing* x = nodes_.crossing(b, l, a);
          if (!x) throw std::out_of_range("extract_dmc: internal error: crossing not computed");
          const auto [db, dl] = nodes_.rel(b, (l & 3) + (a == 0), (l >> 2 & 3) + (a == 1), (l >> 4) + (a == 2));
          const std::int32_t r = nodes_.claim_refined();
          eb.add(&nodes_.node(b, l), &nodes_.node(db, dl), &nodes_.refined(r));
          x->refined = r;
        }
        B.xwant[a] = 0;
      }
      evals_local.local() += solve(eb, 60, 0.0, grads_local.local());
    });
    for (std::size_t n : evals_local) st_.evaluations += n;
    for (std::size_t n : grads_local) st_.gradient_evaluations += n;
  }

  std::vector<Key> feature_step() {
    std::vector<Key> cells = sorted_surface();
    std::vector<std::vector<Proposal>> props(cells.size());
    std::vector<char> sharp(cells.size(), 0);
    parallel(cells.size(), [&](std::size_t i) { sharp[i] = detect(cells[i], props[i], false); });
    st_.smooth_cells = smooth_cells_.load();
    refine_sharp(cells, sharp);
    parallel(cells.size(), [&](std::size_t i) {
      if (sharp[i]) detect(cells[i], props[i], true);
    });
    std::vector<Proposal> all;
    for (auto& v : props) all.insert(all.end(), v.begin(), v.end());
    std::sort(all.begin(), all.end(), [](const Proposal& a, const Proposal& b) {
      if (a.node != b.node) return a.node < b.node;
      if (a.priority != b.priority) return a.priority > b.priority;
      if (a.length != b.length) return a.length > b.length;
      return a.cell < b.cell;
    });
    std::vector<Proposal> chosen;
    for (std::size_t i = 0; i < all.size(); ++i) {
      if (i > 0 && all[i].node == all[i - 1].node) continue;
      chosen.push_back(all[i]);
    }
    // Lattice points not yet evaluated (a corner found just beyond the crossed cells),
    // and their 6-neighbours.
    std::vector<Key> keys;
    for (const Proposal& p : chosen) {
      keys.push_back(p.node);
      for (int q = 0; q < 6; ++q) {
          int d[3] = {ki(p.node), kj(p.node), kk(p.node)};
          d[q / 2] += q % 2 ? 1 : -1;
          if (node_in_grid(d[0], d[1], d[2])) keys.push_back(key(d[0], d[1], d[2]));
        }
    }
    ensure(keys);
    // The moves keep each point's sign (a tiny step into or out of the solid from the
    // feature), so the lattice's inside/outside topology is the one after step 1: an
    // outside point pulled onto an edge would otherwise join the edge to the body
    // around outside points (handles). Exception: a corner point outside with an inside
    // 6-neighbour turns inside (the tip of a thin part grows to its apex).
    std::vector<Proposal> apply;
    std::vector<char> want;
    for (const Proposal& p : chosen) {
      const Node& nd = nodes_.at(p.node);
      // A point moved into a thin gap stays there.
      if (nd.flags & (kFixed | kGap)) continue;
      bool inside = nd.val < 0;
      if (!inside) {
        // Pulled onto the feature, an outside point turns inside (so the surface follows
        // the feature), except next to a thin gap, which it would close.
        inside = true;
        for (int q = 0; q < 6 && inside; ++q) {
          int d[3] = {ki(p.node), kj(p.node), kk(p.node)};
          d[q / 2] += q % 2 ? 1 : -1;
          if (!node_in_grid(d[0], d[1], d[2])) continue;
          const auto it = nodes_.find(key(d[0], d[1], d[2]));
          if (it != nullptr && (it->flags & kGap)) inside = false;
        }
      }
      Proposal q = p;
      q.pos += inside ? p.nudge : Vec3d(-p.nudge);
      // Stay inside Omega (the nudge may cross its border).
      const Vec3d cen = upos(p.node);
      for (int a = 0; a < 3; ++a)
        q.pos[a] = std::clamp(q.pos[a], cen[a] - 0.5 * h_, std::nextafter(cen[a] + 0.5 * h_, cen[a]));
      apply.push_back(q);
      want.push_back(inside);
    }
    // f at the new places, a block's proposals taken together (values_near; apply is
    // in key order, so a block's are consecutive).
    std::vector<double> v(apply.size());
    {
      std::vector<Vec3d> xs(apply.size());
      for (std::size_t i = 0; i < apply.size(); ++i) xs[i] = apply[i].pos;
      values_by_block(xs, v, [&](std::size_t i) { return BlockIndex::block_of(apply[i].node); });
      for (double& x : v) x = std::isfinite(x - opt_.iso) ? x - opt_.iso : h_;
    }
    st_.evaluations += apply.size();
    // MC takes a lattice edge between two inside points as inside. A point turned inside
    // whose edge to an inside neighbour leaves the solid (two slabs' rims across a thin
    // slot) would join separate parts: it keeps its place.
    std::unordered_map<Key, std::size_t> index;
    for (std::size_t i = 0; i < apply.size(); ++i)
      if ((v[i] < 0) == bool(want[i])) index.emplace(apply[i].node, i);
    std::vector<std::pair<std::size_t, Vec3d>> checks;  // (flipped proposal, other end)
    std::vector<std::size_t> other;
    for (std::size_t i = 0; i < apply.size(); ++i) {
      if (!index.count(apply[i].node) || !want[i] || nodes_.at(apply[i].node).val < 0) continue;
      for (int q = 0; q < 6; ++q) {
        int d[3] = {ki(apply[i].node), kj(apply[i].node), kk(apply[i].node)};
        d[q / 2] += q % 2 ? 1 : -1;
        if (!node_in_grid(d[0], d[1], d[2])) continue;
        const Key r = key(d[0], d[1], d[2]);
        const auto jt = index.find(r);
        Vec3d rp;
        if (jt != index.end()) {
          if (!want[jt->second]) continue;
          rp = apply[jt->second].pos;
          other.push_back(jt->second);
        } else {
          Node tmp;
          const Node* it = known(r, tmp);
          if (it == nullptr || !(it->val < 0)) continue;
          rp = it->pos;
          other.push_back(SIZE_MAX);
        }
        checks.emplace_back(i, rp);
      }
    }
    std::vector<char> leaves(checks.size(), 0);
    {
      // Three points along each edge, a block's checks taken together (checks are in
      // proposal order, so a block's are consecutive).
      std::vector<Vec3d> xs(3 * checks.size());
      std::vector<double> vs(xs.size());
      for (std::size_t c = 0; c < checks.size(); ++c) {
        const Vec3d& a = apply[checks[c].first].pos;
        for (int k = 0; k < 3; ++k) xs[3 * c + std::size_t(k)] = a + 0.25 * (k + 1) * (checks[c].second - a);
      }
      values_by_block(xs, vs, [&](std::size_t i) { return BlockIndex::block_of(apply[checks[i / 3].first].node); });
      for (std::size_t i = 0; i < xs.size(); ++i)
        if (!(vs[i] - opt_.iso < 0)) leaves[i / 3] = 1;
    }
    st_.evaluations += 3 * checks.size();
    std::vector<char> veto(apply.size(), 0);
    for (std::size_t c = 0; c < checks.size(); ++c)
      if (leaves[c]) {
        veto[checks[c].first] = 1;
        if (other[c] != SIZE_MAX) veto[other[c]] = 1;
      }
    std::vector<Key> moved;
    for (std::size_t i = 0; i < apply.size(); ++i) {
      Node& nd = nodes_.at(apply[i].node);
      if ((v[i] < 0) != bool(want[i])) continue;  // the nudge did not give the sign
      if (veto[i]) {
        ++st_.vetoed;
        continue;
      }
      nd.pos = apply[i].pos;
      nd.val = v[i];
      nd.flags |= apply[i].priority ? kCorner : kEdge;
      ++(apply[i].priority ? st_.moved_corner : st_.moved_edge);
      moved.push_back(apply[i].node);
    }
    fill_turns(moved);
    return moved;
  }

  // Where the chain of points on an edge turns a lattice corner, the outside point in
  // the turn, next to the body, would leave a tunnel between chain and body (a handle).
  // It moves to the inside sample of its Omega nearest to its chain neighbours.
  void fill_turns(std::vector<Key>& moved) {
    std::vector<Key> cand;
    for (Key p : moved)
      for (int q = 0; q < 6; ++q) {
        int d[3] = {ki(p), kj(p), kk(p)};
        d[q / 2] += q % 2 ? 1 : -1;
        if (node_in_grid(d[0], d[1], d[2])) cand.push_back(key(d[0], d[1], d[2]));
      }
    std::sort(cand.begin(), cand.end());
    cand.erase(std::unique(cand.begin(), cand.end()), cand.end());
    std::vector<Key> todo;
    std::vector<Vec3d> target;
    for (Key o : cand) {
      const auto it = nodes_.find(o);
      if (it == nullptr || (it->flags & (kFixed | kGap | kBary | kEdge | kCorner)) || it->val < 0)
        continue;
      int chain = 0, body = 0;
      Vec3d sum = Vec3d::Zero();
      for (int q = 0; q < 6; ++q) {
        int d[3] = {ki(o), kj(o), kk(o)};
        d[q / 2] += q % 2 ? 1 : -1;
        if (!node_in_grid(d[0], d[1], d[2])) continue;
        Node tmp;
        const Node* jt = known(key(d[0], d[1], d[2]), tmp);
        if (jt == nullptr || !(jt->val < 0)) continue;
        if (jt->flags & (kEdge | kCorner)) {
          ++chain;
          sum += jt->pos;
        } else {
          ++body;
        }
      }
      if (chain >= 2 && body >= 1) {
        todo.push_back(o);
        target.push_back(sum / chain);
      }
    }
    std::vector<char> ok(todo.size(), 0);
    std::vector<Vec3d> pos(todo.size());
    std::vector<double> value(todo.size());
    // The samples in order of distance to the target (ties in sampling order): the first
    // inside one is the nearest, so the search stops there.
    tbb::enumerable_thread_specific<std::size_t> evals_local(0);
    parallel(todo.size(), [&](std::size_t i) {
      const Vec3d c0 = upos(todo[i]);
      const double step = h_ / m_;
      std::vector<std::pair<double, int>> order;
      order.reserve(std::size_t(m_) * m_ * m_);
      auto sample = [&](int s) {
        const int a = s / (m_ * m_), b = s / m_ % m_, c = s % m_;
        return Vec3d(c0 + Vec3d((a + 0.5) * step, (b + 0.5) * step, (c + 0.5) * step) - Vec3d::Constant(0.5 * h_));
      };
      for (int s = 0; s < m_ * m_ * m_; ++s) order.emplace_back((sample(s) - target[i]).squaredNorm(), s);
      std::sort(order.begin(), order.end());
      std::size_t evals = 0;
      for (const auto& [dd, s] : order) {
        const Vec3d x = sample(s);
        const double v = g(x);
        ++evals;
        if (!(v < 0)) continue;
        pos[i] = x, value[i] = v, ok[i] = 1;
        break;
      }
      evals_local.local() += evals;
    });
    for (std::size_t n : evals_local) st_.evaluations += n;
    for (std::size_t i = 0; i < todo.size(); ++i) {
      if (!ok[i]) continue;
      Node& nd = nodes_.at(todo[i]);
      nd.pos = pos[i];
      nd.val = value[i];
      nd.flags |= kEdge;
      ++st_.filled_turns;
      moved.push_back(todo[i]);
    }
  }

  // ---------------------------------------------------------------- step 3
  Mesh build_mesh() {
    const std::vector<Key> surface = sorted_surface();
    st_.surface_cells = surface.size();
    const auto& table = mc::triangle_table();
    const auto& ec = mc::edge_corners();
    // Per cell (key order) its configuration, then its first face (prefix sum); the
    // faces' crossings in parallel; vertex ids by first use in face order (serial), so
    // the mesh is the same for any thread count.
    std::vector<std::uint8_t> cfgs(surface.size());
    std::vector<std::uint32_t> handle(surface.size());  // block << 6 | local index
    parallel(surface.size(), [&](std::size_t i) {
      const std::int32_t b = nodes_.block_of(surface[i]);
      const int l = Lattice::local(surface[i]);
      handle[i] = std::uint32_t(b) << 6 | std::uint32_t(l);
      cfgs[i] = std::uint8_t(config(b, l));
    });
    std::vector<std::size_t> first(surface.size() + 1, 0);
    for (std::size_t i = 0; i < surface.size(); ++i) first[i + 1] = first[i] + table[cfgs[i]].size();
    // Faces hold crossing indices until the vertex ids replace them.
    Mesh mesh;
    mesh.faces.resize(first.back());
    parallel(surface.size(), [&](std::size_t i) {
      const std::int32_t b = std::int32_t(handle[i] >> 6);
      const int l = int(handle[i] & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
      std::size_t f = first[i];
      for (const auto& tri : table[cfgs[i]]) {
        for (int t = 0; t < 3; ++t) {
          const int c0 = ec[tri[t]][0];
          const auto [xb, xl] = nodes_.rel(b, li + (c0 & 1), lj + (c0 >> 1 & 1), lk + (c0 >> 2 & 1));
          const std::uint32_t x = nodes_.crossing_index(xb, xl, tri[t] / 4);
          if (x == Lattice::kNoCrossing) throw std::out_of_range("extract_dmc: internal error: crossing not computed");
          mesh.faces[f][t] = int(x);
        }
        ++f;
      }
    });
    std::vector<const Crossing*> edges;
    for (Face& fc : mesh.faces)
      for (int t = 0; t < 3; ++t) {
        Crossing& x = nodes_.crossing_at(std::uint32_t(fc[t]));
        if (x.vid < 0) {
          x.vid = int(edges.size());
          edges.push_back(&x);
        }
        fc[t] = x.vid;
      }
    mesh.vertices.resize(edges.size());
    if (opt_.normals) mesh.normals.resize(edges.size());
    parallel(edges.size(), [&](std::size_t v) {
      const Crossing& x = *edges[v];
      mesh.vertices[v] = x.pos.cast<float>();
      if (opt_.normals) mesh.normals[v] = x.normal.cast<float>();
    });
    tbb::enumerable_thread_specific<std::size_t> degenerate(0);
    parallel(mesh.faces.size(), [&](std::size_t f) {
      const Face& fc = mesh.faces[f];
      const Vec3f e1 = mesh.vertices[fc[1]] - mesh.vertices[fc[0]];
      const Vec3f e2 = mesh.vertices[fc[2]] - mesh.vertices[fc[0]];
      if (!(e1.cross(e2).norm() > 0)) ++degenerate.local();
    });
    for (std::size_t n : degenerate) st_.degenerate_faces += n;
    if (opt_.untrusted == UntrustedRegions::kLeaveOpen && !mesh.faces.empty()) drop_untrusted(mesh);
    return mesh;
  }

  void drop_untrusted(Mesh& mesh) {
    std::vector<char> keep(mesh.faces.size());
    parallel(mesh.faces.size(), [&](std::size_t fi) {
      const Face& fc = mesh.faces[fi];
      const Vec3d centroid = (mesh.vertices[fc[0]] + mesh.vertices[fc[1]] + mesh.vertices[fc[2]]).cast<double>() / 3;
      keep[fi] = f_.trusted(centroid);
    });
    std::vector<int> remap(mesh.vertices.size(), -1);
    Mesh out;
    for (std::size_t fi = 0; fi < mesh.faces.size(); ++fi) {
      if (!keep[fi]) {
        ++st_.dropped_faces;
        continue;
      }
      Face fc = mesh.faces[fi];
      for (int t = 0; t < 3; ++t) {
        int& r = remap[fc[t]];
        if (r < 0) {
          r = int(out.vertices.size());
          out.vertices.push_back(mesh.vertices[fc[t]]);
          if (opt_.normals) out.normals.push_back(mesh.normals[fc[t]]);
        }
        fc[t] = r;
      }
      out.faces.push_back(fc);
    }
    mesh = std::move(out);
  }

  const ImplicitFunction& f_;
  const DmcOptions& opt_;
  mutable std::atomic<std::size_t> smooth_cells_{0};  // detect(): cells left alone as smooth
  tbb::task_arena arena_;
  Vec3d lo_;
  double h_ = 0;
  int n_[3] = {1, 1, 1};
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

}  // namespace

Mesh extract_dmc(const ImplicitFunction& f, const Aabb& box, int resolution, const DmcOptions& opt,
                 DmcStats* stats) {
  if (!box.valid() || !all_finite({box.min, box.max})) throw InvalidInput("extract_dmc: invalid bounding box");
  if (resolution < 1 || resolution > (1 << 20))
    throw InvalidInput("extract_dmc: resolution must be in [1, 2^20]");
  if (!((box.max - box.min).maxCoeff() > 0)) throw InvalidInput("extract_dmc: degenerate bounding box");
  if (opt.threads < 0) throw InvalidInput("extract_dmc: threads must be >= 0");
  if (!(opt.search_step >= 0) || !std::isfinite(opt.search_step))
    throw InvalidInput("extract_dmc: search_step must be >= 0 (0 = h / 5)");
  if (opt.refine_steps < 0 || opt.refine_steps > 64) throw InvalidInput("extract_dmc: refine_steps must be in [0, 64]");
  if (!(opt.theta_sharp >= -1 && opt.theta_sharp <= 1) || !(opt.phi_corner >= 0 && opt.phi_corner <= 1))
    throw InvalidInput("extract_dmc: theta_sharp must be in [-1, 1] and phi_corner in [0, 1]");
  if (!std::isfinite(opt.iso)) throw InvalidInput("extract_dmc: iso must be finite");
  Dmc dmc(f, box, resolution, opt);
  return dmc.run(stats);
}

Mesh extract_dmc(const MpuSurface& surface, int resolution, DmcOptions options, DmcStats* stats) {
  const Aabb box = extraction_box(surface);
  options.seeds = surface.points();
  options.close_at_box = true;
  return extract_dmc(static_cast<const ImplicitFunction&>(surface), box, resolution, options, stats);
}

}  // namespace station
