#include "reconstruct/detail/dmc_internal.h"

namespace station::detail::dmc {

bool Dmc::search(Key p, bool want_inside, Vec3d& pos, double& value) const {
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

bool Dmc::neighbour_value(Key p, std::int32_t b, int l, int axis, int step, double& v) const {
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

bool Dmc::cheap_candidate(const Node& nd, const Neighbours& nb, double h) {
  double slope = 0;
  for (int q = 0; q < 6; ++q) {
    if (!nb.has[q]) continue;
    slope = std::max(slope, std::abs(nb.v[q] - nd.val) / h);
  }
  return !(std::abs(nd.val) > 1.3 * h * slope * 1.5) || slope == 0;
}

bool Dmc::lattice_gradient(const Node& nd, const Neighbours& nb, Vec3d& gr) const {
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

bool Dmc::lattice_thick(Key p, std::int32_t b, int l, const Node& nd, const Vec3d& gr) const {
  const double gn = gr.norm();
  if (!(gn > 0) || !std::isfinite(gn)) return false;
  int a = 0;
  for (int c = 1; c < 3; ++c)
    if (std::abs(gr[c]) > std::abs(gr[a])) a = c;
  // One h along the normal is 1 / |n_a| steps along the axis (a plane's).
  const double reach = gn / std::abs(gr[a]);
  // Towards the near surface: against grad f outside (f > 0), along it inside.
  const int step = (nd.val < 0) == (gr[a] > 0) ? 1 : -1;
  const bool inside = nd.val < 0;
  double prev = nd.val, crossing = -1;
  for (int k = 1; k <= kThickSteps; ++k) {
    double v;
    if (!neighbour_value(p, b, l, a, k * step, v)) return false;
    const bool other = (v < 0) != inside;
    if (crossing < 0) {
      if (!other) {
        prev = v;
        continue;
      }
      // The near surface between steps k - 1 and k (linear).
      crossing = k - 1 + std::abs(prev) / (std::abs(prev) + std::abs(v));
    } else if (!other) {
      return false;  // back on its side within reach of the crossing: thin
    }
    if (k >= crossing + reach) return true;
  }
  return false;
}

bool Dmc::probe(const Node& nd, char role) const {
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

void Dmc::probe_round(ProbeBatch& batch, const std::vector<int>& at, std::vector<int>& thin) const {
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

void Dmc::probe_first_wave(ProbeBatch& batch, std::vector<Key>& todo, std::size_t& probes, std::size_t& gradients) const {
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

std::vector<Key> Dmc::first_wave_todo() {
  tbb::enumerable_thread_specific<std::vector<Key>> todo_local;
  tbb::enumerable_thread_specific<std::vector<std::int32_t>> marked_local;
  tbb::enumerable_thread_specific<std::size_t> probed_local(0), exact_local(0), probes_local(0), thick_local(0);
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
          Vec3d gr = Vec3d::Zero();
          const bool has_grad = lattice_gradient(nd, nb, gr);
          // Most of the lattice's thick parts need no probe (the values beyond the
          // near surface are there); only with the lattice's gradient (f about linear).
          if (has_grad && lattice_thick(p, cb, cl, nd, gr)) {
            ++thick_local.local();
          } else {
            batch.nodes.push_back(&nd);
            batch.keys.push_back(p);
            batch.grads.push_back(gr);
            batch.has_grad.push_back(has_grad);
          }
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
  for (std::size_t n : thick_local) st_.lattice_thick += n;
  for (const auto& v : marked_local)
    for (std::int32_t b : v) nodes_.blk(b).mark = 0;
  std::vector<Key> todo;
  for (const auto& v : todo_local) todo.insert(todo.end(), v.begin(), v.end());
  std::sort(todo.begin(), todo.end());
  return todo;
}

std::vector<Key> Dmc::barycentre_step() {
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
    // With the untrusted surface dropped, the floods stay within the walk's reach too
    // (beyond it nothing is kept, and a flood there would walk the extrapolation the
    // walk left out, a search at every point).
    parallel(spread.size(), [&](std::size_t si) {
      const auto [p, kind] = spread[si];
      if (beyond_reach(upos(p))) return;
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
    // (items skipped above add nothing here: they listed no missing blocks)
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
        Node fresh_node;
        make_node(k, fresh_node);
        if (nodes_.enter(b, l, fresh_node))
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

void Dmc::bridge(std::vector<Key>& moved) {
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

void Dmc::prune_islands(std::vector<Key>& moved) {
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

}  // namespace station::detail::dmc
