#include "reconstruct/dmc.h"

#include "reconstruct/detail/dmc_internal.h"
#include "reconstruct/mpu.h"
#include "core/threads.h"

namespace station::detail::dmc {

Mesh Dmc::run(DmcStats* stats) {
  using Clock = std::chrono::steady_clock;
  auto t0 = Clock::now();
  {
    std::vector<std::uint64_t> start;
    for (Key c : seed_cells())
      start.push_back(std::uint64_t(nodes_.block(ki(c) >> 2, kj(c) >> 2, kk(c) >> 2)) << 6 | std::uint64_t(Lattice::local(c)));
    traverse(start, !opt_.seeds.empty());
  }
  st_.seconds_traversal = seconds_since(t0);

  t0 = Clock::now();
  std::vector<Key> moved;
  if (opt_.barycentre || opt_.thin_gaps) moved = barycentre_step();
  if (!moved.empty()) update_surface(moved);
  st_.seconds_barycentre = seconds_since(t0);
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
  st_.seconds_features = seconds_since(t0);
  t0 = Clock::now();
  if (!crossings_done) compute_crossings();
  Mesh mesh = build_mesh();
  if (opt_.report)
    for (std::size_t b = 0; b < nodes_.block_count(); ++b)
      for (std::uint64_t m = nodes_.blk(std::int32_t(b)).present; m; m &= m - 1) {
        const int l = __builtin_ctzll(m);
        const Key p = nodes_.point(std::int32_t(b), l);
        const Node& nd = nodes_.node(std::int32_t(b), l);
        // The flags a move leaves (not kFixed, a window's own, nor kSearched).
        opt_.report(off_[0] + ki(p), off_[1] + kj(p), off_[2] + kk(p),
                    DmcPoint{nd.pos, nd.val, std::uint8_t(nd.flags & ~(kFixed | kSearched))});
      }
  st_.seconds_mesh = seconds_since(t0);
  if (stats) *stats = st_;
  return mesh;
}

void Dmc::ensure(std::vector<Key>& keys) {
  std::size_t m = 0;
  std::vector<std::uint32_t> fresh;
  Key last = ~Key(0);  // block of the previous key (runs of keys share blocks: scan lines)
  std::int32_t b = Lattice::kNone;
  for (Key k : keys) {
    const Key bk = BlockIndex::block_of(k);
    if (bk != last) b = nodes_.block(ki(k) >> 2, kj(k) >> 2, kk(k) >> 2), last = bk;
    const int l = Lattice::local(k);
    Node fresh_node;
    make_node(k, fresh_node);
    if (nodes_.enter(b, l, fresh_node)) {
      keys[m++] = k;
      fresh.push_back(std::uint32_t(b) << 6 | std::uint32_t(l));
    }
  }
  keys.resize(m);
  evaluate(fresh);
}

void Dmc::evaluate(std::vector<std::uint32_t> fresh) {
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
      if (is_given(p, nd)) continue;  // its value came with it
      if (const double* v = scan_value(ki(p), kj(p), kk(p))) {
        nd.val = *v;
        continue;
      }
      at[n] = &nd;
      xs[n++] = nd.pos;
    }
    f_.values_near(xs, n, vs);
    for (int i = 0; i < n; ++i) at[i]->val = lattice_value_from(vs[i], at[i]->flags, at[i]->pos);
    count.local() += std::size_t(n);
  });
  for (std::size_t n : count) st_.evaluations += n;
}

int Dmc::config(std::int32_t b, int l) const {
  const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
  int cfg = 0;
  for (int q = 0; q < 8; ++q) {
    const auto [cb, cl] = nodes_.rel(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
    if (!nodes_.present(cb, cl)) throw std::out_of_range("extract_dmc: internal error: lattice point not evaluated");
    if (nodes_.node(cb, cl).val < 0) cfg |= 1 << q;
  }
  return cfg;
}

std::vector<Key> Dmc::seed_cells() {
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

void Dmc::traverse(const std::vector<std::uint64_t>& start, bool probe_first) {
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
  const auto& faces_of = mc::crossed_faces();
  bool first = probe_first;
  // With the untrusted surface dropped, a crossed cell whose centre lies beyond the
  // trust distance plus kPruneReach cells (beyond_reach) is not part of the surface and
  // does not pass the walk on (as extract_marching_cubes; the margin is wider so that
  // the cells whose faces stay keep every neighbour that moves their vertices).
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
        if (make_node(k, *nd)) continue;  // given, with its value
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
        nd.val = lattice_value_from(vs[t], nd.flags, nd.pos);
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
      if (beyond_reach(lo_ + h_ * Vec3d(i + 0.5, j + 0.5, k + 0.5))) {
        __atomic_fetch_and(&B.surface, ~m, __ATOMIC_RELAXED);
        return;
      }
      B.cfg[l] = std::uint8_t(cfg);
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

bool Dmc::visit(std::int32_t b, int l, std::vector<std::int32_t>& marked) {
  Lattice::Block& B = nodes_.blk(b);
  const std::uint64_t m = std::uint64_t(1) << l;
  if ((__atomic_load_n(&B.surface, __ATOMIC_RELAXED) & m) || (__atomic_load_n(&B.mark, __ATOMIC_RELAXED) & m))
    return false;
  const std::uint64_t old = __atomic_fetch_or(&B.mark, m, __ATOMIC_RELAXED);
  if (old & m) return false;
  if (!old) marked.push_back(b);
  return true;
}

void Dmc::update_surface(const std::vector<Key>& moved) {
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

}  // namespace station::detail::dmc

namespace station {

using detail::dmc::Dmc;

Mesh extract_dmc(const ImplicitFunction& f, const Aabb& box, int resolution, const DmcOptions& opt,
                 DmcStats* stats) {
  if (opt.window) {
    check_window(*opt.window, "extract_dmc");
  } else {
    if (!box.valid() || !all_finite({box.min, box.max})) throw InvalidInput("extract_dmc: invalid bounding box");
    if (resolution < 1 || resolution > (1 << 20))
      throw InvalidInput("extract_dmc: resolution must be in [1, 2^20]");
    if (!((box.max - box.min).maxCoeff() > 0)) throw InvalidInput("extract_dmc: degenerate bounding box");
  }
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
