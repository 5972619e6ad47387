// Cloud-to-cloud nearest distances, both directions (the core of `station
// eval`): our evaluate(cloud, cloud) against Open3D's
// PointCloud::ComputePointCloudDistance called both ways, on two ~300k-point
// clouds sampled on the mustard bottle (the second with 0.5 mm noise).
#include <omp.h>

#include <algorithm>
#include <numeric>
#include <random>
#include <tuple>

#include <open3d/geometry/PointCloud.h>

#include "core/io.h"
#include "harness.h"
#include "eval/eval.h"

namespace station::bench {

namespace {

constexpr int kPoints = 300000;
constexpr double kNoise = 0.0005;  // metres

Cloud noisy_samples(const Mesh& mesh, unsigned seed, double sigma) {
  Cloud cloud;
  cloud.points = sample_mesh(mesh, kPoints, seed).points;  // positions only, as the anchor sees them
  if (sigma > 0) {
    std::mt19937 rng(seed);
    std::normal_distribution<float> noise(0.f, float(sigma));
    for (Vec3f& p : cloud.points) p += Vec3f(noise(rng), noise(rng), noise(rng));
  }
  return cloud;
}

open3d::geometry::PointCloud to_open3d(const Cloud& cloud) {
  open3d::geometry::PointCloud out;
  out.points_.reserve(cloud.size());
  for (const Vec3f& p : cloud.points) out.points_.push_back(p.cast<double>());
  return out;
}

double mean_of(const std::vector<double>& v) {
  return v.empty() ? 0 : std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
}

double max_of(const std::vector<double>& v) {
  return v.empty() ? 0 : *std::max_element(v.begin(), v.end());
}

}  // namespace

void run_distance_cases(const Options& options, Report& report) {
  const Mesh mustard =
      read_mesh(options.source_dir / "data" / "mustard_bottle" / "textured.obj");
  const Shape a = noisy_samples(mustard, 1, 0);
  const Shape b = noisy_samples(mustard, 2, kNoise);
  open3d::geometry::PointCloud oa = to_open3d(std::get<Cloud>(a));
  open3d::geometry::PointCloud ob = to_open3d(std::get<Cloud>(b));

  auto run_case = [&](const std::string& name, int threads) {
    EvalParams params;
    params.threads = threads;
    EvalResult ours;
    std::vector<double> ab, ba;
    Row row{name, "PointCloud::ComputePointCloudDistance x2"};
    omp_set_num_threads(threads);  // Open3D 0.16 runs these queries in an OpenMP loop
    std::tie(row.ours, row.theirs) = measure_pair(
        options, [&] { ours = evaluate(a, b, params); },
        [&] {
          ab = oa.ComputePointCloudDistance(ob);
          ba = ob.ComputePointCloudDistance(oa);
        });
    omp_set_num_threads(options.threads);
    report.rows.push_back(row);
    return std::make_tuple(ours, ab, ba);
  };

  const std::string label = "nearest distances 2 x " + std::to_string(kPoints / 1000) + "k";
  const auto [ours, ab, ba] = run_case(label, options.threads);
  if (options.threads > 1) run_case(label + ", 1 thread", 1);

  report.note(label + ": ours A->B mean " + format_fixed(ours.a_to_b.mean * 1e6, 3) + " um, max " +
              format_fixed(ours.a_to_b.max * 1e6, 3) + " um; Open3D " + format_fixed(mean_of(ab) * 1e6, 3) +
              " um, " + format_fixed(max_of(ab) * 1e6, 3) + " um; B->A ours " +
              format_fixed(ours.b_to_a.mean * 1e6, 3) + " / " + format_fixed(ours.b_to_a.max * 1e6, 3) +
              " um, Open3D " + format_fixed(mean_of(ba) * 1e6, 3) + " / " +
              format_fixed(max_of(ba) * 1e6, 3) + " um");
  report.note("distances: ours builds both KD-trees (nanoflann, float) and also computes mean, "
              "rms, p95 (sort) and max per direction; Open3D (KDTreeFlann = nanoflann, double) "
              "builds one tree per call and returns the raw distances. Open3D's loop is OpenMP "
              "with omp_get_max_threads() workers, set with omp_set_num_threads to our count");
}

}  // namespace station::bench
