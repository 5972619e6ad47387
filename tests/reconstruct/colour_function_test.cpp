#include "reconstruct/colour_function.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <limits>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <random>
#include <sstream>
#include <string>

#include "core/error.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "core/texture.h"
#include "reconstruct/colour_transfer.h"
#include "eval/eval.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "test_util.h"

namespace station {
namespace {

const Rgb kRed{255, 0, 0}, kBlue{0, 0, 255}, kGreen{0, 255, 0};
using Painter = std::function<Rgb(const Vec3d&)>;

// Points on the unit sphere (Fibonacci spiral) with outward normals, painted.
Cloud sphere_cloud(int n, const Painter& paint, double r = 1.0) {
  Cloud c = test::fibonacci_sphere(n, r);
  for (const Vec3f& d : c.normals) c.colours.push_back(paint(d.cast<double>()));
  return c;
}

// Uniform random points on the unit sphere (held out: not the fitted points).
std::vector<Vec3d> random_sphere_points(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g;
  std::vector<Vec3d> out;
  while (int(out.size()) < n) {
    const Vec3d d(g(rng), g(rng), g(rng));
    if (d.norm() > 1e-6) out.push_back(d.normalized());
  }
  return out;
}

double rgb_error(const std::array<double, 3>& f, const Rgb& c) {
  return std::abs(f[0] - c.r / 255.0) + std::abs(f[1] - c.g / 255.0) + std::abs(f[2] - c.b / 255.0);
}
double rgb_error(const Rgb& a, const Rgb& c) {
  return (std::abs(a.r - c.r) + std::abs(a.g - c.g) + std::abs(a.b - c.b)) / 255.0;
}

// A tilted plane splits the sphere: red above, blue below.
const Vec3d kSplitNormal = Vec3d(0.3, 0.2, 1).normalized();
constexpr double kSplitOffset = 0.1;
double split_distance(const Vec3d& p) { return p.dot(kSplitNormal) - kSplitOffset; }
Rgb half_red_half_blue(const Vec3d& p) { return split_distance(p) > 0 ? kRed : kBlue; }

// Three sectors of azimuth (junctions at the poles), rotated so the junction is
// not on an axis.
Rgb three_sectors(const Vec3d& p) {
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(0.4, Vec3d(1, 0.3, 0).normalized()).toRotationMatrix();
  const Vec3d q = rot * p;
  const double a = std::atan2(q.y(), q.x()) + M_PI;  // [0, 2 pi)
  return a < 2 * M_PI / 3 ? kRed : a < 4 * M_PI / 3 ? kGreen : kBlue;
}

// Area-uniform samples on a textured mesh with face normals and texture colours.
Cloud sample_textured(const TexturedMesh& tm, const Texture& tex, int count, unsigned seed) {
  const Mesh& m = tm.mesh;
  std::vector<double> cum;
  double area = 0;
  for (const Face& f : m.faces) {
    const Vec3d a = m.vertices[f[0]].cast<double>(), b = m.vertices[f[1]].cast<double>(), cc = m.vertices[f[2]].cast<double>();
    area += 0.5 * (b - a).cross(cc - a).norm();
    cum.push_back(area);
  }
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  Cloud out;
  for (int i = 0; i < count; ++i) {
    const int fi = int(std::lower_bound(cum.begin(), cum.end(), u(rng) * area) - cum.begin());
    const Face& f = m.faces[std::min<std::size_t>(fi, m.faces.size() - 1)];
    double s = u(rng), t = u(rng);
    if (s + t > 1) s = 1 - s, t = 1 - t;
    const Vec3d a = m.vertices[f[0]].cast<double>(), b = m.vertices[f[1]].cast<double>(), cc = m.vertices[f[2]].cast<double>();
    out.points.push_back(((1 - s - t) * a + s * b + t * cc).cast<float>());
    out.normals.push_back((b - a).cross(cc - a).normalized().cast<float>());
    out.colours.push_back(surface_colour(tm, tex, int(&f - m.faces.data()), s, t));
  }
  return out;
}

TEST(ColourFunction, HalfRedHalfBlueSphereKeepsItsBoundarySharp) {
  const Cloud c = sphere_cloud(20000, half_red_half_blue);
  const ColourFunction f = fit_colour(c);
  const ColourDiagnostics& d = f.diagnostics();
  std::printf("sphere 20k: leaves A %zu B %zu, grown %zu, unconverged %zu, e_col %.3g, fit %.3f s\n",
              d.leaves_by_type[0], d.leaves_by_type[1], d.grown_leaves, d.unconverged_leaves, d.e_col, d.fit_seconds);
  EXPECT_GT(d.leaves_by_type[1], 0u);
  EXPECT_LT(d.e_col, 1e-3);  // the paper's e_col on noise-free data
  // Held-out points: exact colour beyond 0.02 (about the point spacing, 0.025) of the
  // boundary; within it, the colour is one of the two (no blend) except very close.
  int wrong = 0, blended = 0;
  double max_blend_dist = 0;
  for (const Vec3d& q : random_sphere_points(20000, 3)) {
    const Rgb got = f.rgb(q);
    const double dist = std::abs(split_distance(q));
    const double e = rgb_error(got, half_red_half_blue(q));
    if (dist > 0.02 && e > 2.5 / 255) ++wrong;
    if (rgb_error(got, kRed) > 0.1 && rgb_error(got, kBlue) > 0.1) ++blended, max_blend_dist = std::max(max_blend_dist, dist);
  }
  std::printf("  held-out: wrong %d, blended %d, max blend distance %.4f\n", wrong, blended, max_blend_dist);
  EXPECT_EQ(wrong, 0);
}

// Smoothly varying colour on both sides of a sharp boundary (not piecewise constant):
// Type A quadratics must meet epsilon_col, Type B interpolates. The 8-bit input is
// itself a quantised smooth field (a smooth fit differs from it by ~0.25/255 per
// channel on average, e_col ~ 3e-3), so e_col here sits near 1e-3 (measured 1.46e-3;
// Type A only 1.25e-2).
TEST(ColourFunction, SmoothShadingWithASharpBoundary) {
  auto paint = [](const Vec3d& p) {
    const double t = 0.5 + 0.5 * std::sin(2.0 * p.x() + 1.0 * p.y());  // smooth shading
    auto ch = [](double v) { return std::uint8_t(std::lround(std::clamp(v, 0.0, 255.0))); };
    return split_distance(p) > 0 ? Rgb{ch(150 + 100 * t), ch(40 + 60 * t), ch(30)}
                                 : Rgb{ch(30), ch(80 + 100 * t), ch(120 + 120 * t)};
  };
  const Cloud c = sphere_cloud(20000, paint);
  const ColourFunction f = fit_colour(c);
  ColourParams a_only;
  a_only.type_b = false;
  a_only.n_max = 2000;
  const ColourFunction fa = fit_colour(c, a_only);
  double held = 0;
  const auto qs = random_sphere_points(10000, 37);
  for (const Vec3d& q : qs) held += rgb_error(f.srgb(q), paint(q)) / qs.size();
  std::printf("smooth shading: e_col %.3g (Type A only %.3g), held-out %.3g, leaves A %zu B %zu unconverged %zu\n",
              f.diagnostics().e_col, fa.diagnostics().e_col, held, f.diagnostics().leaves_by_type[0],
              f.diagnostics().leaves_by_type[1], f.diagnostics().unconverged_leaves);
  EXPECT_LT(f.diagnostics().e_col, 2e-3);
  EXPECT_GT(fa.diagnostics().e_col, 5 * f.diagnostics().e_col);
  EXPECT_LT(held, 6e-3);
}

// Smooth shading quantised to 8 bits: the paper's eq. 4 (0.1 L*) fails on the
// quantisation alone, so its cells split down to split_min_points; measuring each
// point's residual beyond its own quantisation (the default) keeps larger cells, as
// accurate on held-out points.
TEST(ColourFunction, QuantisationAloneDoesNotSplitCells) {
  auto paint = [](const Vec3d& p) {
    const double t = 0.5 + 0.5 * std::sin(1.5 * p.x() + 0.7 * p.y() - 0.4 * p.z());
    auto ch = [](double v) { return std::uint8_t(std::lround(std::clamp(v, 0.0, 255.0))); };
    return Rgb{ch(60 + 150 * t), ch(140 - 60 * t), ch(40 + 90 * t)};
  };
  const Cloud c = sphere_cloud(20000, paint);
  ColourParams paper;
  paper.quantisation_tolerance = false;
  const ColourFunction fp = fit_colour(c, paper);
  const ColourFunction fq = fit_colour(c);
  double held_p = 0, held_q = 0;
  const auto qs = random_sphere_points(10000, 41);
  for (const Vec3d& q : qs) {
    held_p += rgb_error(fp.srgb(q), paint(q)) / qs.size();
    held_q += rgb_error(fq.srgb(q), paint(q)) / qs.size();
  }
  const ColourDiagnostics &dp = fp.diagnostics(), &dq = fq.diagnostics();
  std::printf("quantised shading: leaves %zu (unconverged %zu) -> %zu (%zu); held-out %.3g -> %.3g; e_col %.3g -> %.3g\n",
              dp.leaves, dp.unconverged_leaves, dq.leaves, dq.unconverged_leaves, held_p, held_q, dp.e_col, dq.e_col);
  // Measured: 2,929 -> 1,672 leaves, held-out 0.00262 -> 0.00263, e_col 0.00237 -> 0.00249.
  EXPECT_LT(double(dq.leaves), 0.7 * double(dp.leaves));
  EXPECT_LE(dq.unconverged_leaves, dp.unconverged_leaves);
  EXPECT_LT(held_q, 1.1 * held_p);
  EXPECT_LT(dq.e_col, 4e-3);  // three channels, each within about half an 8-bit step
}

// The paper's Tables 1-2: Type A only (N_max = 2000, as the paper) blurs the boundary;
// with Type B e_col is at least 10x lower.
TEST(ColourFunction, TypeBIsTenTimesMoreAccurateThanTypeAOnly) {
  const Cloud c = sphere_cloud(12000, half_red_half_blue);
  ColourParams a_only;
  a_only.type_b = false;
  a_only.n_max = 2000;
  const ColourFunction fa = fit_colour(c, a_only), fab = fit_colour(c);
  const double ea = fa.diagnostics().e_col, eab = fab.diagnostics().e_col;
  std::printf("e_col Type A only %.3g, A+B %.3g\n", ea, eab);
  EXPECT_EQ(fa.diagnostics().leaves_by_type[1], 0u);
  EXPECT_GT(ea, 1e-3);  // the blur is real
  EXPECT_LT(eab, 1e-3);
  EXPECT_GT(ea, 10 * eab);
  // The same on held-out points (not interpolated by construction).
  double ha = 0, hab = 0;
  const auto qs = random_sphere_points(10000, 5);
  for (const Vec3d& q : qs) {
    ha += rgb_error(fa.srgb(q), half_red_half_blue(q)) / qs.size();
    hab += rgb_error(fab.srgb(q), half_red_half_blue(q)) / qs.size();
  }
  std::printf("held-out mean error Type A only %.3g, A+B %.3g\n", ha, hab);
  EXPECT_GT(ha, 3 * hab);
}

// Option (a): at a three-colour junction the paper's two clusters blend the third
// colour into one of them; one-vs-rest boundaries keep every boundary sharp.
TEST(ColourFunction, ThreeColourJunctionStaysSharpWithMultiColour) {
  const Cloud c = sphere_cloud(12000, three_sectors);
  ColourParams multi;
  multi.multi_colour = true;
  const ColourFunction f2 = fit_colour(c), f3 = fit_colour(c, multi);
  EXPECT_GT(f3.diagnostics().multi_colour_leaves, 0u);
  EXPECT_EQ(f2.diagnostics().multi_colour_leaves, 0u);
  // Held-out points within 0.25 of the two junctions (the sectors' poles): mean error
  // and the number of blended colours (none of the three).
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(0.4, Vec3d(1, 0.3, 0).normalized()).toRotationMatrix();
  const Vec3d pole = rot.transpose() * Vec3d::UnitZ();
  std::vector<Vec3d> qs;
  for (const Vec3d& q : random_sphere_points(60000, 9))
    if ((q - pole).norm() < 0.25 || (q + pole).norm() < 0.25) qs.push_back(q);
  auto measure = [&](const ColourFunction& f, double& mean, int& blended) {
    mean = 0;
    blended = 0;
    for (const Vec3d& q : qs) {
      const Rgb got = f.rgb(q);
      mean += rgb_error(got, three_sectors(q)) / qs.size();
      if (rgb_error(got, kRed) > 0.15 && rgb_error(got, kGreen) > 0.15 && rgb_error(got, kBlue) > 0.15) ++blended;
    }
  };
  double m2, m3;
  int b2, b3;
  measure(f2, m2, b2);
  measure(f3, m3, b3);
  std::printf("junction (%zu points near the poles): two clusters mean %.3g blended %d (e_col %.3g); multi mean %.3g blended %d (e_col %.3g)\n", qs.size(), m2,
              b2, f2.diagnostics().e_col, m3, b3, f3.diagnostics().e_col);
  // Measured: mean 0.090 -> 0.054, blended 176 -> 11 of 1857.
  EXPECT_LT(m3, 0.75 * m2);
  EXPECT_LT(4 * b3, b2);
}

// On the mesh extracted from the MPU surface of the same points, the band of vertices
// whose colour is wrong or a blend is narrower than one grid cell.
TEST(ColourFunction, TransitionOnTheExtractedMeshIsNarrowerThanOneCell) {
  const Cloud c = sphere_cloud(20000, half_red_half_blue);
  const MpuSurface s = fit_mpu(c);
  MarchingCubesStats st;
  Mesh mesh = extract_marching_cubes(s, 48, {}, &st);
  const double h = st.cell_size;
  auto band = [&](const Mesh& m) {
    double width = 0;  // max |distance to the boundary| of a vertex not of its side's colour
    for (std::size_t i = 0; i < m.vertices.size(); ++i) {
      const Vec3d p = m.vertices[i].cast<double>().normalized();
      if (rgb_error(m.colours[i], half_red_half_blue(p)) > 0.1) width = std::max(width, std::abs(split_distance(p)));
    }
    return 2 * width;
  };
  colour_mesh(mesh, fit_colour(c));
  const double ours = band(mesh);
  Mesh knn = mesh;
  transfer_colours(knn, c);
  std::printf("transition band: colour function %.4f, k-NN transfer %.4f, cell %.4f, spacing %.4f\n", ours, band(knn), h,
              std::sqrt(4 * M_PI / c.size()));
  EXPECT_LT(ours, h);
}

// The transition measured as bench/surface_bench.cpp does (measure_colour_transition,
// reconstruct/eval.h; docs/benchmarks.md, "Colour transition on the two-colour sphere").
using Transition = ColourTransition;
Transition measure_transition(const Mesh& mesh, const std::function<double(const Vec3d&)>& signed_distance,
                              const Rgb& a, const Rgb& b, double h) {
  return measure_colour_transition(mesh, signed_distance, a, b, h);
}

// Issue 7's targets on a grid finer than the sampling, as in the bench (cell 0.78 x the
// mean point spacing, random points): the colour band on the mesh is narrower than one
// cell, and no vertex more than one cell from the boundary takes the other side's colour
// where the samples decide it. Where the nearest input point itself has the other colour
// (a gap in the sampling along the boundary: e.g. red samples right at the boundary and
// the nearest blue ones 1-2 spacings beyond it), no local method can know the side; the
// test checks that every such vertex is one of those. Measured (seeds 53 / 5; seed 2
// alike): paper blend band 2.24 / 2.38 cells, side_consensus 0 (no band vertex); wrong
// side beyond one cell 0 / 1 (1.01 cells, where the nearest sample has the other colour;
// nearest-sample colours have 6 / 8 such vertices, up to 1.85 cells).
TEST(ColourFunction, TransitionIsNarrowerThanOneCellOnAGridFinerThanTheSampling) {
  const Rgb red{220, 30, 30}, blue{30, 40, 200};
  auto side = [&](const Vec3d& p) { return split_distance(p) > 0 ? blue : red; };
  auto distance = [](const Vec3d& p) { return split_distance(p.normalized()); };
  for (unsigned seed : {53u, 5u}) {
    Cloud c;
    for (const Vec3d& d : random_sphere_points(40000, seed)) {
      c.points.push_back(d.cast<float>());
      c.normals.push_back(d.cast<float>());
      c.colours.push_back(side(d));
    }
    const double spacing = std::sqrt(4 * M_PI / double(c.size()));
    MpuParams mp;
    mp.threads = 2;
    const MpuSurface s = fit_mpu(c, mp);
    MarchingCubesOptions mo;
    mo.threads = 2;
    MarchingCubesStats st;
    Mesh mesh = extract_marching_cubes(s, 160, mo, &st);
    const double h = st.cell_size;
    ColourParams cp, paper, rbf;
    cp.threads = paper.threads = rbf.threads = 2;
    paper.side_consensus = false;
    paper.linear_boundary = rbf.linear_boundary = false;
    const ColourFunction f = fit_colour(c, cp);
    Mesh mesh_paper = mesh, mesh_rbf = mesh, nearest = mesh;
    colour_mesh(mesh, f, 2);
    colour_mesh(mesh_paper, fit_colour(c, paper), 2);
    colour_mesh(mesh_rbf, fit_colour(c, rbf), 2);
    transfer_colours(nearest, c, {1, 2});
    const Transition t = measure_transition(mesh, distance, red, blue, h);
    const Transition tp = measure_transition(mesh_paper, distance, red, blue, h);
    const Transition tr = measure_transition(mesh_rbf, distance, red, blue, h);
    const Transition tn = measure_transition(nearest, distance, red, blue, h);
    // Wrong-side vertices beyond one cell whose nearest input point has their true colour.
    std::size_t decided_far = 0;
    for (std::size_t i = 0; i < mesh.vertices.size(); ++i) {
      const Vec3d p = mesh.vertices[i].cast<double>();
      const Rgb truth = side(p.normalized());
      if (std::abs(distance(p)) > h && rgb_error(mesh.colours[i], truth) > 0.5 && rgb_error(nearest.colours[i], truth) < 0.1)
        ++decided_far;
    }
    std::printf("seed %u: %zu vertices, cell %.4f (%.2f spacings), e_col %.3g, B leaves %zu\n", seed, mesh.vertices.size(), h,
                h / spacing, f.diagnostics().e_col, f.diagnostics().leaves_by_type[1]);
    for (const auto& [name, x] : {std::pair<const char*, const Transition&>{"default", t}, {"RBF boundary", tr},
                                  {"paper", tp}, {"nearest sample", tn}})
      std::printf("  %-14s band %3zu vertices, width %.2f cells; wrong side %3zu, %zu beyond one cell, farthest %.2f cells\n",
                  name, x.band, x.width / h, x.wrong, x.wrong_far, x.max_wrong / h);
    std::printf("  linear boundaries: %zu of %zu Type B leaves\n", f.diagnostics().linear_boundaries,
                f.diagnostics().leaves_by_type[1]);
    std::printf("  side consensus: wrong side beyond one cell where the nearest sample is right: %zu\n", decided_far);
    EXPECT_LT(t.width, h);
    EXPECT_EQ(decided_far, 0u);
    EXPECT_LE(t.wrong_far, tn.wrong_far);
    EXPECT_LT(f.diagnostics().e_col, 1e-3);
    // With the RBF boundary (side consensus only) the farthest wrong-side vertex was
    // 0.94 / 1.01 cells away (seeds 53 / 5), where the sampling leaves a gap along the
    // boundary; the max-margin line of each cell, held by all its samples, keeps every
    // vertex within 0.4 cells and takes a third of the wrong-side vertices.
    EXPECT_LT(tr.max_wrong, 1.25 * h);
    EXPECT_LT(t.max_wrong, 0.5 * h);
    EXPECT_LT(3 * t.wrong, 2 * tr.wrong);
    EXPECT_GT(f.diagnostics().linear_boundaries, f.diagnostics().leaves_by_type[1] / 2);
  }
}

// Option (b): colour noise makes the paper's test see boundaries everywhere (and the
// RBFs then interpolate the noise); the noise test keeps them where they are.
TEST(ColourFunction, NoiseRobustCellsIgnoreColourNoise) {
  const Rgb warm{200, 70, 60}, cold{60, 70, 200};
  auto truth = [&](const Vec3d& p) { return split_distance(p) > 0 ? warm : cold; };
  std::mt19937 rng(11);
  std::normal_distribution<double> noise(0, 12);
  const Cloud c = sphere_cloud(12000, [&](const Vec3d& p) {
    const Rgb t = truth(p);
    auto ch = [&](int v) { return std::uint8_t(std::clamp<long>(std::lround(v + noise(rng)), 0, 255)); };
    return Rgb{ch(t.r), ch(t.g), ch(t.b)};
  });
  ColourParams robust;
  robust.noise_robust = true;
  const ColourFunction fp = fit_colour(c), fr = fit_colour(c, robust);
  // Held-out error against the noise-free truth, away from the boundary, and the share
  // of the surface that is Type B.
  auto measure = [&](const ColourFunction& f, double& err, double& type_b) {
    err = type_b = 0;
    int n = 0;
    const auto qs = random_sphere_points(8000, 13);
    for (const Vec3d& q : qs) {
      type_b += (f.dominant_type(q) == ColourCellType::kB) / double(qs.size());
      if (std::abs(split_distance(q)) < 0.05) continue;
      err += rgb_error(f.srgb(q), truth(q));
      ++n;
    }
    err /= n;
  };
  double ep, er, bp, br;
  measure(fp, ep, bp);
  measure(fr, er, br);
  std::printf("noise: paper B leaves %zu (surface share %.3f) error %.4f; robust B leaves %zu (share %.3f, rejected %zu) error %.4f\n",
              fp.diagnostics().leaves_by_type[1], bp, ep, fr.diagnostics().leaves_by_type[1], br,
              fr.diagnostics().rejected_type_b, er);
  EXPECT_LT(br, 0.5 * bp);
  EXPECT_LT(er, 0.6 * ep);
  EXPECT_GT(fr.diagnostics().leaves_by_type[1], 0u);  // the real boundary stays Type B
}

// Option (c): off the surface (an offset of the sphere) the colour is taken at the
// projection onto the MPU zero set.
TEST(ColourFunction, OffsetSurfaceTakesTheProjectedColour) {
  const Cloud c = sphere_cloud(12000, half_red_half_blue);
  const MpuSurface s = fit_mpu(c);
  ColourParams paper;
  paper.side_consensus = false;
  // The paper's blend, where off-surface queries degrade most, and the default.
  for (const ColourParams& p : {paper, ColourParams{}}) {
    ColourFunction plain = fit_colour(c, p);
    ColourFunction projected = plain;
    projected.set_surface(&s);
    // Measured (12k points, unit sphere), paper's blend: without projection the error
    // grows with the offset (0.0054 at 0.02, 0.0099 at 0.08, 0.022 at 0.2); with it, it
    // stays at the on-surface level (0.0056). With side_consensus (default) the off-surface
    // error grows later (0.0050 at 0.08, 0.011 at 0.2; projected 0.0057).
    for (double offset : {0.02, 0.08, 0.12, 0.2}) {
      double ep = 0, eq = 0;
      const auto qs = random_sphere_points(6000, 17);
      for (const Vec3d& q : qs) {
        for (double sign : {-1.0, 1.0}) {
          const Vec3d x = q * (1 + sign * offset);
          ep += rgb_error(plain.srgb(x), half_red_half_blue(q)) / (2 * qs.size());
          eq += rgb_error(projected.srgb(x), half_red_half_blue(q)) / (2 * qs.size());
        }
      }
      std::printf("%s, offset %.2f: error without projection %.4f, with %.4f\n",
                  p.side_consensus ? "side consensus" : "paper blend", offset, ep, eq);
      EXPECT_LT(eq, 0.007);
      if (offset >= (p.side_consensus ? 0.2 : 0.08)) {
        EXPECT_LT(eq, 0.7 * ep);
      }
    }
  }
}

// N_max raised above the dense limit (400 nodes): Type B systems go through the sparse
// Cholesky and give the same sharp result.
TEST(ColourFunction, LargeTypeBCellsUseTheSparseSolver) {
  const Cloud c = sphere_cloud(5000, half_red_half_blue);
  ColourParams big;
  big.n_max = 500;
  const ColourFunction f = fit_colour(c, big);
  EXPECT_GT(f.diagnostics().leaves_by_type[1], 0u);
  EXPECT_EQ(f.diagnostics().fallback_type_a, 0u);
  EXPECT_LT(f.diagnostics().e_col, 1e-3);
  int wrong = 0;
  for (const Vec3d& q : random_sphere_points(5000, 41))
    if (std::abs(split_distance(q)) > 0.04) wrong += rgb_error(f.rgb(q), half_red_half_blue(q)) > 2.5 / 255;
  EXPECT_EQ(wrong, 0);
}

TEST(ColourFunction, BadInputGivesErrorsOrFiniteColours) {
  Cloud none = sphere_cloud(100, half_red_half_blue);
  none.colours.clear();
  EXPECT_THROW(fit_colour(none), InvalidInput);
  EXPECT_THROW(fit_colour(Cloud{}), InvalidInput);
  Cloud nan = sphere_cloud(100, half_red_half_blue);
  nan.points[3].x() = NAN;
  EXPECT_THROW(fit_colour(nan), InvalidInput);
  Cloud same;
  for (int i = 0; i < 20; ++i) same.points.push_back(Vec3f(1, 2, 3)), same.colours.push_back(kRed);
  EXPECT_THROW(fit_colour(same), InvalidInput);
  Cloud mismatched = sphere_cloud(100, half_red_half_blue);
  mismatched.colours.pop_back();
  EXPECT_THROW(fit_colour(mismatched), InvalidInput);
  ColourParams bad;
  bad.n_max = 5;
  EXPECT_THROW(fit_colour(sphere_cloud(100, half_red_half_blue), bad), InvalidInput);
  EXPECT_THROW(ColourFunction().rgb(Vec3d::Zero()), InvalidInput);

  auto expect_finite = [](const ColourFunction& f, const Rgb* want) {
    for (const Vec3d& q : random_sphere_points(500, 23)) {
      for (const Vec3d& x : {q, Vec3d(3 * q), Vec3d(0.1 * q)}) {
        const Lab l = f.lab(x);
        ASSERT_TRUE(std::isfinite(l[0]) && std::isfinite(l[1]) && std::isfinite(l[2]));
        if (want && x == q) {
          EXPECT_LE(rgb_error(f.rgb(x), *want), 1.0 / 255);
        }
      }
    }
  };
  // One colour everywhere: exactly that colour.
  const Rgb grey{90, 120, 150};
  expect_finite(fit_colour(sphere_cloud(3000, [&](const Vec3d&) { return grey; })), &grey);
  // One odd point (a one-point cluster): its cells stay Type B with a constant cluster.
  const ColourFunction odd = fit_colour(sphere_cloud(3000, [&](const Vec3d& p) { return p.z() > 0.9995 ? kGreen : grey; }));
  EXPECT_GT(odd.diagnostics().constant_clusters, 0u);
  expect_finite(odd, nullptr);
  // Duplicated points with different colours, without normals.
  Cloud dup = sphere_cloud(2000, half_red_half_blue);
  dup.normals.clear();
  for (int i = 0; i < 200; ++i) {
    dup.points.push_back(dup.points[i * 7]);
    dup.colours.push_back(kGreen);
  }
  expect_finite(fit_colour(dup), nullptr);
  // Fewer points than n_min.
  expect_finite(fit_colour(sphere_cloud(6, half_red_half_blue)), nullptr);
}

TEST(ColourFunction, WithoutNormalsAndDeterministicAcrossThreads) {
  Cloud c = sphere_cloud(6000, three_sectors);
  c.normals.clear();
  ColourParams p1, p2;
  p1.threads = 1;
  p2.threads = 2;
  p1.multi_colour = p2.multi_colour = true;
  const ColourFunction a = fit_colour(c, p1), b = fit_colour(c, p2);
  EXPECT_LT(a.diagnostics().e_col, 1e-3);
  EXPECT_EQ(a.diagnostics().leaves, b.diagnostics().leaves);
  for (const Vec3d& q : random_sphere_points(2000, 29)) {
    const Lab la = a.lab(q), lb = b.lab(q);
    for (int k = 0; k < 3; ++k) ASSERT_EQ(la[k], lb[k]);
  }
  std::vector<Vec3f> xs;
  for (const Vec3d& q : random_sphere_points(100, 31)) xs.push_back(q.cast<float>());
  const std::vector<Rgb> batch = a.rgbs(xs);
  for (std::size_t i = 0; i < xs.size(); ++i) EXPECT_TRUE(batch[i] == a.rgb(xs[i].cast<double>()));
}

// e_col over a strided sample (ColourParams::e_col_max_points, the surface stage's
// kEColPoints): exactly e_col() on every (n / m)-th point, and all points at or below m.
TEST(ColourFunction, EColOverAStridedSampleOfThePoints) {
  const Cloud c = sphere_cloud(6000, three_sectors);
  ColourParams all, some, enough;
  some.e_col_max_points = 1000;
  enough.e_col_max_points = 6000;
  const ColourFunction fa = fit_colour(c, all), fs = fit_colour(c, some), fe = fit_colour(c, enough);
  EXPECT_EQ(fa.diagnostics().e_col_points, 6000u);
  EXPECT_EQ(fe.diagnostics().e_col_points, 6000u);
  EXPECT_EQ(fe.diagnostics().e_col, fa.diagnostics().e_col);
  EXPECT_EQ(fs.diagnostics().e_col_points, 1000u);
  Cloud every_sixth;
  for (std::size_t i = 0; i < c.size(); i += 6) {
    every_sixth.points.push_back(c.points[i]);
    every_sixth.colours.push_back(c.colours[i]);
  }
  ASSERT_EQ(every_sixth.size(), 1000u);
  EXPECT_EQ(fs.diagnostics().e_col, fa.e_col(every_sixth));
  EXPECT_NE(fs.diagnostics().e_col, fa.diagnostics().e_col);  // a sample, not the whole cloud
  EXPECT_GT(fs.diagnostics().e_col, 0);
}

// labs() groups nearby points and walks the octree once per group: the values must be
// lab()'s bit for bit, wherever the points are (on, off and far from the surface, in
// any order, non-finite ones {0, 0, 0}).
TEST(ColourFunction, BatchedLabsAreLabBitForBit) {
  const Cloud c = sphere_cloud(8000, three_sectors);
  ColourParams p;
  p.multi_colour = true;
  const ColourFunction f = fit_colour(c, p);
  std::vector<Vec3f> xs;
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> offset(-0.2f, 0.2f);
  for (const Vec3d& q : random_sphere_points(3000, 37)) xs.push_back(q.cast<float>() * (1.0f + offset(rng)));
  xs.push_back(Vec3f(5, 5, 5));
  xs.push_back(Vec3f(std::nanf(""), 0, 0));
  xs.push_back(Vec3f(0, std::numeric_limits<float>::infinity(), 0));
  std::shuffle(xs.begin(), xs.end(), rng);
  for (int threads : {1, 2}) {
    const std::vector<Lab> batch = f.labs(xs, threads);
    ASSERT_EQ(batch.size(), xs.size());
    for (std::size_t i = 0; i < xs.size(); ++i) {
      const Lab one = f.lab(xs[i].cast<double>());
      for (int k = 0; k < 3; ++k) ASSERT_EQ(batch[i][k], one[k]) << "point " << i << " channel " << k;
    }
  }
}

// Real colour: points sampled on the bundled YCB mustard bottle with its texture's
// colours (printed label).
TEST(ColourFunction, MustardBottleTextureRegression) {
  const TexturedMesh tm = read_textured_mesh(test::source_dir() / "data/mustard_bottle/textured.obj");
  const Texture tex = load_texture(tm.texture);
  auto sample = [&](int n, unsigned seed) { return sample_textured(tm, tex, n, seed); };
  const Cloud c = sample(20000, 1), held = sample(10000, 2);
  ColourParams p;
  p.threads = 2;
  const ColourFunction f = fit_colour(c, p);
  ColourParams a_only = p;
  a_only.type_b = false;
  a_only.n_max = 2000;
  const ColourFunction fa = fit_colour(c, a_only);
  const ColourDiagnostics& d = f.diagnostics();
  const double held_ab = f.e_col(held), held_a = fa.e_col(held);
  std::printf("mustard 20k: A %zu B %zu (unconverged A %zu), fit %.3f s; e_col input %.3g (A only %.3g), held-out %.3g (A only %.3g)\n",
              d.leaves_by_type[0], d.leaves_by_type[1], d.unconverged_leaves, d.fit_seconds, d.e_col,
              fa.diagnostics().e_col, held_ab, held_a);
  // Measured (20k points): e_col 1.13e-2 on the input points (Type A only: 5.1e-2),
  // 0.072 on held-out points (Type A only 0.085; the label's print is finer than the
  // sampling). Thresholds a bit above.
  EXPECT_LT(d.e_col, 0.013);
  EXPECT_LT(d.e_col, 0.5 * fa.diagnostics().e_col);
  EXPECT_LT(held_ab, 0.08);
  EXPECT_LT(held_ab, held_a);
}

// The Stanford dragon (all 15 turntable scans of the team's data set, merged with
// Stanford's alignment, no normals) painted half red / half blue. Skipped where
// ../shared is absent (CI).
TEST(ColourFunction, DragonHalfRedHalfBlue) {
  const std::filesystem::path dir = test::source_dir() / "../shared/data/stanford_dragon_stand";
  if (!std::filesystem::exists(dir / "dragonStandRight.conf")) GTEST_SKIP() << "no " << dir;
  const std::vector<Vec3f> pts = merge_stanford_scans(dir / "dragonStandRight.conf", 4).points;
  ASSERT_GT(pts.size(), 50000u);
  const Aabb box = bounding_box(pts);
  const Vec3d mid = box.center().cast<double>();
  const Vec3d split = Vec3d(1, 0.3, 0.2).normalized();
  auto paint = [&](const Vec3f& p) { return (p.cast<double>() - mid).dot(split) > 0 ? kRed : kBlue; };
  Cloud fit, held;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    Cloud& c = i % 3 == 2 ? held : fit;
    c.points.push_back(pts[i]);
    c.colours.push_back(paint(pts[i]));
  }
  ColourParams p;
  p.threads = 2;
  const ColourFunction f = fit_colour(fit, p);
  ColourParams a_only = p;
  a_only.type_b = false;
  a_only.n_max = 2000;
  const ColourFunction fa = fit_colour(fit, a_only);
  const ColourDiagnostics& d = f.diagnostics();
  // Held-out points farther than 1 mm (a few spacings) from the boundary: exact.
  int wrong = 0, far = 0;
  for (std::size_t i = 0; i < held.size(); ++i) {
    if (std::abs((held.points[i].cast<double>() - mid).dot(split)) < 1e-3) continue;
    ++far;
    wrong += rgb_error(f.rgb(held.points[i].cast<double>()), held.colours[i]) > 2.5 / 255;
  }
  std::printf("dragon %zu points: A %zu B %zu, fit %.3f s, e_col %.3g (Type A only %.3g), held-out e_col %.3g, wrong %d of %d\n",
              fit.size(), d.leaves_by_type[0], d.leaves_by_type[1], d.fit_seconds, d.e_col, fa.diagnostics().e_col,
              f.e_col(held), wrong, far);
  EXPECT_LT(d.e_col, 1e-3);
  EXPECT_GT(fa.diagnostics().e_col, 10 * d.e_col);
  EXPECT_LT(wrong, far / 1000 + 1);
}

// Real sharp colour edges: the YCB Rubik's cube (six sticker colours, black gaps,
// sticker corners where three colours meet), the bundled copy (texture downsampled to
// 2048^2, data/rubiks_cube/README.md), kept as a regression test.
TEST(ColourFunction, RubiksCubeStickerEdges) {
  const TexturedMesh tm = read_textured_mesh(test::source_dir() / "data/rubiks_cube/textured.obj");
  const Texture tex = load_texture(tm.texture);
  const Cloud c = sample_textured(tm, tex, 20000, 1), held = sample_textured(tm, tex, 5000, 2);
  ColourParams p;
  p.threads = 2;
  ColourParams a_only = p;
  a_only.type_b = false;
  a_only.n_max = 2000;
  const ColourFunction f = fit_colour(c, p), fa = fit_colour(c, a_only);
  // Measured on the bundled copy: e_col 3.6e-3 (Type A only 2.2e-2); held-out 0.038
  // (0.042). (On the 4096^2 original: 3.9e-3 / 2.3e-2, 0.038 / 0.044.) Thresholds a
  // bit above.
  std::printf("rubik 20k: e_col A+B %.3g (A only %.3g); held-out %.3g (A only %.3g); B leaves %zu, fit %.3f s\n",
              f.diagnostics().e_col, fa.diagnostics().e_col, f.e_col(held), fa.e_col(held),
              f.diagnostics().leaves_by_type[1], f.diagnostics().fit_seconds);
  EXPECT_GT(f.diagnostics().leaves_by_type[1], 500u);  // the sticker edges are boundaries
  EXPECT_LT(f.diagnostics().e_col, 0.0045);
  EXPECT_LT(f.diagnostics().e_col, 0.5 * fa.diagnostics().e_col);
  EXPECT_LT(f.e_col(held), 0.042);
  EXPECT_LT(f.e_col(held), fa.e_col(held));
}

}  // namespace
}  // namespace station

namespace station {
namespace {

/// The unit sphere as an implicit, trusted only above z = 0 (where the points are).
struct UpperTrusted : ImplicitFunction {
  double value(const Vec3d& x) const override { return x.norm() - 1; }
  Vec3d gradient(const Vec3d& x) const override { return x.normalized(); }
  bool trusted(const Vec3d& x) const override { return x.z() > 0; }
};

TEST(ColourMeshTrusted, UntrustedVerticesTakeTheNearestInputColours) {
  // Points on the upper hemisphere only, colour varying with height.
  const Mesh sphere = test::icosphere(4, 1.0);
  Cloud c;
  for (const Vec3f& v : sphere.vertices) {
    if (v.z() <= 0.05f) continue;
    c.points.push_back(v);
    c.normals.push_back(v.normalized());
    c.colours.push_back(Rgb{std::uint8_t(100 + 150 * v.z()), 40, std::uint8_t(200 - 150 * v.z())});
  }
  const ColourFunction f = fit_colour(c);
  Mesh m = test::icosphere(3, 1.0);
  const std::size_t below = std::count_if(m.vertices.begin(), m.vertices.end(), [](const Vec3f& v) { return v.z() <= 0; });
  const std::size_t n = colour_mesh(m, f, UpperTrusted{}, c);
  EXPECT_EQ(n, below);
  Mesh nn = test::icosphere(3, 1.0);
  transfer_colours(nn, c, {4, 0});
  Mesh plain = test::icosphere(3, 1.0);
  colour_mesh(plain, f);
  for (std::size_t i = 0; i < m.vertices.size(); ++i) {
    const Rgb expect = m.vertices[i].z() <= 0 ? nn.colours[i] : plain.colours[i];
    EXPECT_EQ(m.colours[i].r, expect.r) << i;
    EXPECT_EQ(m.colours[i].b, expect.b) << i;
  }
}

}  // namespace
}  // namespace station
