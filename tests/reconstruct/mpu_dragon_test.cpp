// MPU on real data: the bundled Stanford dragon scans (every 5th point of 15
// turntable views) merged with Stanford's reference poses. Regression: a closed
// mesh whose distance to the scans is below the scans' mean point spacing.
#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <fstream>
#include <map>
#include <sstream>

#include "core/io.h"
#include "core/stanford_conf.h"
#include "core/normals.h"
#include "eval/eval.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mesh_clean.h"
#include "reconstruct/mpu.h"
#include "test_util.h"

namespace station {
namespace {

// Stanford's alignment, as `station import` reads it (core/stanford_conf.h).
Cloud merged_dragon() {
  return merge_stanford_scans(test::source_dir() / "data/dragon_stand/dragonStandRight.conf");
}

bool closed_manifold(const Mesh& m) {
  std::map<std::pair<int, int>, int> edges;
  for (const Face& f : m.faces)
    for (int k = 0; k < 3; ++k) {
      const int a = f[k], b = f[(k + 1) % 3];
      ++edges[{std::min(a, b), std::max(a, b)}];
    }
  for (const auto& [e, n] : edges)
    if (n != 2) return false;
  return true;
}

TEST(MpuDragon, ClosedMeshWithinTheScansMeanSpacing) {
  Cloud c = merged_dragon();
  ASSERT_GT(c.size(), 50000u);
  c.normals = estimate_normals(c.points, 12);
  orient_normals_mst(c.points, c.normals, 12);
  MpuParams p;
  p.epsilon0 = std::max(p.epsilon0, suggest_epsilon0(c));
  const MpuSurface s = fit_mpu(c, p);
  Mesh m = extract_marching_cubes(s, 96);
  remove_small_components(m, 0.01);
  ASSERT_GT(m.faces.size(), 10000u);
  EXPECT_TRUE(closed_manifold(m));
  EvalParams ep;
  ep.mesh_samples = 100000;
  const EvalResult e = evaluate(c, m, ep);  // scans -> mesh: how well the mesh follows the data
  const double spacing = s.diagnostics().mean_spacing;
  std::printf("dragon: %zu points, spacing %.3f mm, epsilon0 %.2g, %zu faces, scans->mesh mean %.3f mm, "
              "p95 %.3f mm, mesh->scans mean %.3f mm\n",
              c.size(), spacing * 1000, p.epsilon0, m.faces.size(), e.a_to_b.mean * 1000, e.a_to_b.p95 * 1000,
              e.b_to_a.mean * 1000);
  EXPECT_LT(e.a_to_b.mean, spacing);
  EXPECT_LT(e.a_to_b.p95, 2 * spacing);
  // Not asserted: mesh -> scans. Where the scans leave large parts unseen (the
  // stand's open bottom), MPU's extrapolation flares out to the extraction box and
  // is capped there (mean ~8 mm here; docs/mpu.md, "Known limits").
}

}  // namespace
}  // namespace station
