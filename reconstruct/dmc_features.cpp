#include "reconstruct/detail/dmc_internal.h"

namespace station::detail::dmc {

std::size_t Dmc::crossings(const Node* const* a, const Node* const* b, int n, int steps, double done_error, CrossingBatch& cb,
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

std::size_t Dmc::solve(EdgeBatch& eb, int steps, double done_error, std::size_t& gradients) const {
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

void Dmc::want_crossings(std::int32_t b, int l) {
  const auto& ec = mc::edge_corners();
  const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
  const int cfg = nodes_.blk(b).cfg[l];
  for (int e = 0; e < 12; ++e) {
    if (!crossed(cfg, e)) continue;
    const int c0 = ec[e][0];
    const auto [cb, cl] = nodes_.rel(b, li + (c0 & 1), lj + (c0 >> 1 & 1), lk + (c0 >> 2 & 1));
    Lattice::set_bit(nodes_.blk(cb).xwant[e / 4], cl);
  }
}

void Dmc::compute_crossings() {
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

bool Dmc::detect(Key c, std::vector<Proposal>& out, bool refined) const {
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

void Dmc::refine_sharp(const std::vector<Key>& cells, const std::vector<char>& sharp) {
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

std::vector<Key> Dmc::feature_step() {
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

void Dmc::fill_turns(std::vector<Key>& moved) {
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

}  // namespace station::detail::dmc
