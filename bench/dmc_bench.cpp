// Mesh extraction (issue 6, docs/dmc.md): our sparse marching cubes and Deformed
// Marching Cubes (s = h/5) on analytic functions (sphere, the paper's contact lens,
// a thin spike, a rotated cube) at 128^3 and 256^3, and on MPU surfaces (a lumpy
// sphere; the dragon of ../shared/data/stanford_dragon_stand when present); and at
// 512^3 both against VTK's vtkFlyingEdges3D on the sphere and the lens, its
// vtkImageData filled from the same function (whole run: allocation + fill +
// contour; the contour alone is timed separately and given in the notes).
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <tuple>
#include <vector>

#include <Eigen/Geometry>

#include <vtkFlyingEdges3D.h>
#include <vtkFloatArray.h>
#include <vtkImageData.h>
#include <vtkPointData.h>
#include <vtkPolyData.h>
#include <vtkSMPTools.h>
#include <vtkSmartPointer.h>
#include <vtkVersion.h>

#include "core/normals.h"
#include "core/stanford_conf.h"
#include "harness.h"
#include "reconstruct/dmc.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "reconstruct/sdm.h"

namespace station::bench {

namespace {

Aabb centred_box(double half) {
  Aabb box;
  box.extend(Vec3f(float(-half), float(-half), float(-half)));
  box.extend(Vec3f(float(half), float(half), float(half)));
  return box;
}

// Sphere of radius r about c (a signed distance).
struct BenchSphere final : ImplicitFunction {
  Vec3d c{0.01, 0.02, -0.03};
  double r = 0.8;
  double value(const Vec3d& x) const override { return (x - c).norm() - r; }
  Vec3d gradient(const Vec3d& x) const override { return (x - c).normalized(); }
};

// Fujimoto et al.'s contact lens: max(|x|^2 - 9, 8.9 - |x|^2, y), a half shell
// 0.0167 thick, on [-3.2, 3.2]^3.
struct BenchLens final : ImplicitFunction {
  double value(const Vec3d& x) const override {
    const double q = x.squaredNorm();
    return std::max({q - 9.0, 8.9 - q, x.y()});
  }
  Vec3d gradient(const Vec3d& x) const override {
    const double q = x.squaredNorm();
    const double outer = q - 9.0, inner = 8.9 - q;
    if (outer >= inner && outer >= x.y()) return 2.0 * x;
    if (inner >= x.y()) return -2.0 * x;
    return Vec3d(0, 1, 0);
  }
};

// Ball of radius 0.5 with a thin cone along `axis`: radius `base` at the centre,
// apex at distance `length`.
struct BenchSpike final : ImplicitFunction {
  Vec3d axis = Vec3d(1.0, 0.7, 0.4).normalized();
  double base = 0.02, length = 0.9;
  double cone(const Vec3d& x, Vec3d* grad) const {
    const double along = x.dot(axis);
    const Vec3d off = x - along * axis;
    const double rho = off.norm();
    const double slope = base / length;
    const double c = 1.0 / std::sqrt(1.0 + slope * slope);
    const double lateral = (rho - (length - along) * slope) * c;
    if (grad) {
      if (lateral >= -along) {
        const Vec3d dir = rho > 0 ? Vec3d(off / rho) : Vec3d(axis.unitOrthogonal());
        *grad = (dir + slope * axis) * c;
      } else {
        *grad = -axis;
      }
    }
    return std::max(lateral, -along);
  }
  double value(const Vec3d& x) const override { return std::min(x.norm() - 0.5, cone(x, nullptr)); }
  Vec3d gradient(const Vec3d& x) const override {
    Vec3d g;
    const double c = cone(x, &g);
    return x.norm() - 0.5 <= c ? Vec3d(x.normalized()) : g;
  }
};

// Cube of half side 0.52, rotated 30 degrees about x, then 30 degrees about y.
struct BenchCube final : ImplicitFunction {
  Eigen::Matrix3d rotation;
  double half = 0.52;
  BenchCube() {
    rotation = (Eigen::AngleAxisd(M_PI / 6, Vec3d::UnitY()) * Eigen::AngleAxisd(M_PI / 6, Vec3d::UnitX()))
                   .toRotationMatrix();
  }
  double value(const Vec3d& x) const override {
    return (rotation.transpose() * x).cwiseAbs().maxCoeff() - half;
  }
  Vec3d gradient(const Vec3d& x) const override {
    const Vec3d local = rotation.transpose() * x;
    int axis = 0;
    local.cwiseAbs().maxCoeff(&axis);
    Vec3d g = Vec3d::Zero();
    g[axis] = local[axis] < 0 ? -1.0 : 1.0;
    return rotation * g;
  }
};

struct Case {
  std::string name;
  const ImplicitFunction* f;
  Aabb box;
};

/// VTK's whole run on a resolution^3-cell grid over `box` (cubic cells of the box's
/// longest side / resolution, as ours): image allocated and filled with f at the
/// grid points (float, in parallel), then vtkFlyingEdges3D at 0. Returns triangles.
vtkSmartPointer<vtkImageData> filled_image(const ImplicitFunction& f, const Aabb& box, int resolution) {
  const Vec3f size = box.max - box.min;
  const double h = double(size.maxCoeff()) / resolution;
  int dims[3];
  for (int a = 0; a < 3; ++a) dims[a] = int(std::lround(size[a] / h)) + 1;
  auto image = vtkSmartPointer<vtkImageData>::New();
  image->SetDimensions(dims);
  image->SetOrigin(box.min.x(), box.min.y(), box.min.z());
  image->SetSpacing(h, h, h);
  auto values = vtkSmartPointer<vtkFloatArray>::New();
  values->SetName("f");
  values->SetNumberOfTuples(vtkIdType(dims[0]) * dims[1] * dims[2]);
  float* out = values->GetPointer(0);
  tbb::parallel_for(tbb::blocked_range<int>(0, dims[2]), [&](const tbb::blocked_range<int>& r) {
    for (int k = r.begin(); k != r.end(); ++k)
      for (int j = 0; j < dims[1]; ++j) {
        float* row = out + (vtkIdType(k) * dims[1] + j) * dims[0];
        for (int i = 0; i < dims[0]; ++i)
          row[i] = float(f.value(Vec3d(box.min.x() + i * h, box.min.y() + j * h, box.min.z() + k * h)));
      }
  });
  image->GetPointData()->SetScalars(values);
  return image;
}

vtkIdType flying_edges(vtkImageData* image) {
  auto fe = vtkSmartPointer<vtkFlyingEdges3D>::New();
  fe->SetInputData(image);
  fe->SetValue(0, 0.0);
  fe->Update();
  return fe->GetOutput()->GetNumberOfPolys();
}

}  // namespace

void run_dmc_cases(const Options& options, Report& report) {
  vtkSMPTools::Initialize(options.threads);
  const BenchSphere sphere;
  const BenchLens lens;
  const BenchSpike spike;
  const BenchCube cube;
  const std::vector<Case> cases = {{"sphere", &sphere, centred_box(1)},
                                   {"lens", &lens, centred_box(3.2)},
                                   {"spike", &spike, centred_box(1)},
                                   {"cube", &cube, centred_box(1)}};
  MarchingCubesOptions mc_options;
  mc_options.threads = options.threads;
  DmcOptions dmc_options;
  static_cast<MarchingCubesOptions&>(dmc_options) = mc_options;  // s = h/5 by default

  // 256^3 rows take seconds: at most 3 timed runs.
  Options few = options;
  few.repetitions = std::min(options.repetitions, 3);

  for (int resolution : {128, 256}) {
    for (const Case& c : cases) {
      const std::string label =
          c.name + " " + std::to_string(resolution) + "^3: DMC (s = h/5) vs our MC";
      std::size_t mc_faces = 0, dmc_faces = 0;
      DmcStats stats;
      Row row{label, "our sparse MC (target: DMC <= 1.25x)"};
      std::tie(row.ours, row.theirs) = measure_pair(
          resolution >= 256 ? few : options,
          [&] { dmc_faces = extract_dmc(*c.f, c.box, resolution, dmc_options, &stats).faces.size(); },
          [&] { mc_faces = extract_marching_cubes(*c.f, c.box, resolution, mc_options).faces.size(); });
      report.rows.push_back(row);
      report.note(label + ": triangles DMC " + std::to_string(dmc_faces) + ", MC " +
                  std::to_string(mc_faces) + "; DMC Omega searches " + std::to_string(stats.searched) +
                  ", moved (thin / corner / edge) " + std::to_string(stats.moved_barycentre) + " / " +
                  std::to_string(stats.moved_corner) + " / " + std::to_string(stats.moved_edge) +
                  "; phases walk / step 1 / step 2 / mesh " + format_fixed(stats.seconds_traversal, 2) +
                  " / " + format_fixed(stats.seconds_barycentre, 2) + " / " +
                  format_fixed(stats.seconds_features, 2) + " / " + format_fixed(stats.seconds_mesh, 2) + " s");
    }
  }

  // An MPU surface (evaluations dear): a lumpy sphere, 10,242 points with approximate
  // normals, fit_mpu defaults.
  {
    const Mesh ico = make_icosphere_template(5);
    Cloud cloud;
    for (const Vec3f& v : ico.vertices) {
      const float r = 1.0f + 0.1f * std::sin(5 * v.x()) * std::cos(4 * v.y());
      cloud.points.push_back(v * r);
      cloud.normals.push_back(v.normalized());
    }
    const MpuSurface mpu = fit_mpu(cloud);
    const int resolution = 128;
    std::size_t mc_faces = 0, dmc_faces = 0;
    const std::string label = "MPU lumpy sphere " + std::to_string(resolution) + "^3: DMC vs our MC";
    Row row{label, "our sparse MC (target: DMC <= 2x)"};
    std::tie(row.ours, row.theirs) = measure_pair(
        few, [&] { dmc_faces = extract_dmc(mpu, resolution, dmc_options).faces.size(); },
        [&] { mc_faces = extract_marching_cubes(mpu, resolution, mc_options).faces.size(); });
    report.rows.push_back(row);
    report.note(label + ": " + std::to_string(cloud.size()) +
                " points (icosphere level 5, radius 1 + 0.1 sin 5x cos 4y), triangles DMC " +
                std::to_string(dmc_faces) + ", MC " + std::to_string(mc_faces));
  }

  // The MPU surface of the Stanford dragon (the case): the full scans of
  // ../shared/data/stanford_dragon_stand merged with the .conf poses, every 5th point,
  // normals estimated and oriented (k = 12), fit_mpu with epsilon0 from
  // suggest_epsilon0 (as tests/reconstruct/mpu_dragon_test.cpp). Skipped without ../shared.
  {
    const fs::path conf = options.shared_dir / "stanford_dragon_stand" / "dragonStandRight.conf";
    if (!options.use_shared || !fs::exists(conf)) {
      report.note("MPU dragon: skipped (" + conf.string() + " missing; the row needs ../shared)");
    } else {
      Cloud cloud = merge_stanford_scans(conf, 5);
      cloud.normals = estimate_normals(cloud.points, 12, options.threads);
      orient_normals_mst(cloud.points, cloud.normals, 12);
      MpuParams params;
      params.epsilon0 = std::max(params.epsilon0, suggest_epsilon0(cloud));
      const MpuSurface mpu = fit_mpu(cloud, params);
      for (int resolution : {128, 256}) {
        std::size_t mc_faces = 0, dmc_faces = 0;
        DmcStats stats;
        const std::string label = "MPU dragon " + std::to_string(resolution) + "^3: DMC vs our MC";
        Row row{label, "our sparse MC (target: DMC <= 2x)"};
        std::tie(row.ours, row.theirs) = measure_pair(
            few, [&] { dmc_faces = extract_dmc(mpu, resolution, dmc_options, &stats).faces.size(); },
            [&] { mc_faces = extract_marching_cubes(mpu, resolution, mc_options).faces.size(); });
        report.rows.push_back(row);
        report.note(label + ": " + std::to_string(cloud.size()) +
                    " points (../shared full scans merged with the .conf poses, every 5th point), triangles DMC " +
                    std::to_string(dmc_faces) + ", MC " + std::to_string(mc_faces) + "; DMC Omega searches " +
                    std::to_string(stats.searched) + ", moved (thin / corner / edge) " +
                    std::to_string(stats.moved_barycentre) + " / " + std::to_string(stats.moved_corner) + " / " +
                    std::to_string(stats.moved_edge) + "; phases walk / step 1 / step 2 / mesh " +
                    format_fixed(stats.seconds_traversal, 2) + " / " + format_fixed(stats.seconds_barycentre, 2) +
                    " / " + format_fixed(stats.seconds_features, 2) + " / " + format_fixed(stats.seconds_mesh, 2) +
                    " s");
      }
    }
  }

  // 512^3 against VTK Flying Edges, sphere and lens; one run per side (no warm-up).
  Options once = options;
  once.warmup = 0;
  once.repetitions = 1;
  const int big = 512;
  for (const Case& c : {cases[0], cases[1]}) {
    const std::string prefix = c.name + " " + std::to_string(big) + "^3: ";
    std::size_t mc_faces = 0, dmc_faces = 0;
    vtkIdType fe_faces = 0;
    auto vtk_whole = [&] {
      vtkSmartPointer<vtkImageData> image = filled_image(*c.f, c.box, big);
      fe_faces = flying_edges(image);
    };
    const std::string anchor = "vtkFlyingEdges3D, fill + contour (" + std::to_string(options.threads) + " threads)";
    Row mc_row{prefix + "our MC (whole extraction)", anchor};
    std::tie(mc_row.ours, mc_row.theirs) = measure_pair(
        once, [&] { mc_faces = extract_marching_cubes(*c.f, c.box, big, mc_options).faces.size(); }, vtk_whole);
    report.rows.push_back(mc_row);
    Row dmc_row{prefix + "DMC (whole extraction)", anchor};
    DmcStats stats;
    std::tie(dmc_row.ours, dmc_row.theirs) = measure_pair(
        once, [&] { dmc_faces = extract_dmc(*c.f, c.box, big, dmc_options, &stats).faces.size(); }, vtk_whole);
    report.rows.push_back(dmc_row);
    // The contour alone, on a grid filled beforehand.
    Timing fill, contour;
    {
      vtkSmartPointer<vtkImageData> image;
      fill = measure(once, [&] { image = filled_image(*c.f, c.box, big); });
      contour = measure(once, [&] { fe_faces = flying_edges(image); });
    }
    report.note(prefix + "triangles MC " + std::to_string(mc_faces) + ", DMC " + std::to_string(dmc_faces) +
                ", Flying Edges " + std::to_string(fe_faces) + "; Flying Edges alone: fill " +
                format_fixed(fill.median_ms, 1) + " ms (+" + format_fixed(fill.peak_mib, 1) +
                " MiB), contour of the filled grid " + format_fixed(contour.median_ms, 1) + " ms (+" +
                format_fixed(contour.peak_mib, 1) + " MiB; " +
                format_fixed(double(big) * big * big / (contour.median_ms * 1e-3) * 1e-9, 2) +
                " G cells/s); DMC phases walk / step 1 / step 2 / mesh " +
                format_fixed(stats.seconds_traversal, 2) + " / " + format_fixed(stats.seconds_barycentre, 2) +
                " / " + format_fixed(stats.seconds_features, 2) + " / " + format_fixed(stats.seconds_mesh, 2) + " s");
  }
  report.note(std::string("dmc: VTK ") + vtkVersion::GetVTKVersion() +
              " (SMP backend TBB, vtkSMPTools::Initialize(" + std::to_string(options.threads) +
              ")); the grid is float, filled in a TBB loop from the same function; Flying Edges "
              "computes normals (its default), so do ours (gradient). Boxes: sphere, spike, cube "
              "[-1, 1]^3, lens [-3.2, 3.2]^3; no seeds (scan lines every resolution/32 cells). "
              "Timed runs: 128^3 rows " + std::to_string(options.repetitions) + ", 256^3 and MPU rows " +
              std::to_string(few.repetitions) + ", 512^3 rows 1 without warm-up");
}

[[maybe_unused]] static const bool registered =
    register_group("dmc", "marching cubes and DMC vs VTK Flying Edges (issue 6)", &run_dmc_cases);

}  // namespace station::bench
