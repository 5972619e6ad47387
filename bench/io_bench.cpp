// Reading point clouds: our read_cloud against PCL (loadPLYFile / loadPCDFile)
// and Open3D (io::ReadPointCloud), on an ASCII PLY range scan (~40k points)
// and a binary_compressed organised PCD (640x480, RGB).
#include <cmath>
#include <limits>
#include <tuple>

#include <open3d/geometry/PointCloud.h>
#include <open3d/io/PointCloudIO.h>
#include <pcl/console/print.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_types.h>

#include "core/error.h"
#include "core/io.h"
#include "core/texture.h"
#include "harness.h"
#include "eval/eval.h"
#include "sim/bench.h"

namespace station::bench {

namespace {

struct Inputs {
  fs::path ply, pcd;
  std::string origin;
};

/// An ASCII PLY of 41,841 xyz points (the size of dragonStandRight_0.ply)
/// sampled on the mustard bottle, written with our ASCII writer.
void generate_ply(const Options& options, const Mesh& mustard, const fs::path& path) {
  Cloud cloud;
  cloud.points = sample_mesh(mustard, 41841, 7).points;
  write_ply(path, cloud, PlyFormat::kAscii);
}

/// A 640x480 organised XYZRGB cloud (NaN where no return) rendered by the
/// simulator, saved binary_compressed by PCL (our station does not write PCD).
void generate_pcd(const Options& options, const fs::path& path) {
  const fs::path obj = options.source_dir / "data" / "mustard_bottle" / "textured.obj";
  TexturedMesh textured = read_textured_mesh(obj);
  Texture texture = textured.texture.empty() ? Texture{} : load_texture(textured.texture);
  SyntheticParams params;
  params.mesh = obj.string();
  params.dropout = 0.01;
  params.colour_noise = 2;
  const sim::Scene scene(std::move(textured), std::move(texture), params);
  const Frame frame = scene.render(0.0, 0);
  const Intrinsics& k = frame.intrinsics;
  pcl::PointCloud<pcl::PointXYZRGB> cloud(std::uint32_t(k.width), std::uint32_t(k.height));
  cloud.is_dense = false;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (int row = 0; row < k.height; ++row)
    for (int col = 0; col < k.width; ++col) {
      const std::size_t i = std::size_t(row) * k.width + col;
      pcl::PointXYZRGB& p = cloud.at(col, row);
      const float z = frame.depth[i];
      if (z > 0) {
        p.x = float((col - k.cx) / k.fx) * z;
        p.y = float((row - k.cy) / k.fy) * z;
        p.z = z;
      } else {
        p.x = p.y = p.z = nan;
      }
      p.r = frame.colour[3 * i];
      p.g = frame.colour[3 * i + 1];
      p.b = frame.colour[3 * i + 2];
    }
  if (pcl::io::savePCDFileBinaryCompressed(path.string(), cloud) < 0)
    throw IoError(path.string() + ": PCL could not write it");
}

Inputs find_inputs(const Options& options) {
  Inputs in;
  const fs::path ply = options.shared_dir / "stanford_dragon_stand" / "dragonStandRight_0.ply";
  const fs::path pcd = options.shared_dir / "coloured_scans" / "office1.pcd";
  if (options.use_shared && fs::exists(ply) && fs::exists(pcd)) {
    in.ply = ply;
    in.pcd = pcd;
    in.origin = "shared data (" + options.shared_dir.lexically_normal().string() + ")";
    return in;
  }
  const fs::path obj = options.source_dir / "data" / "mustard_bottle" / "textured.obj";
  in.ply = options.temp_dir / "scan_ascii.ply";
  in.pcd = options.temp_dir / "organised_binary_compressed.pcd";
  generate_ply(options, read_mesh(obj), in.ply);
  generate_pcd(options, in.pcd);
  in.origin = std::string(options.use_shared ? "shared data not found under " +
                                                   options.shared_dir.lexically_normal().string() + ": "
                                             : "--generate: ") +
              "generated files in a temp dir (ASCII PLY: 41,841 points sampled on the mustard "
              "bottle, our writer; PCD: a 640x480 sim view, XYZRGB, written binary_compressed by PCL)";
  return in;
}

std::string size_text(const fs::path& path) {
  return format_fixed(double(fs::file_size(path)) / (1024.0 * 1024.0), 2) + " MiB";
}

}  // namespace

void run_io_cases(const Options& options, Report& report) {
  pcl::console::setVerbosityLevel(pcl::console::L_ERROR);
  const Inputs in = find_inputs(options);
  report.note("I/O inputs: " + in.origin);

  // Open3D drops NaN points like our reader does (remove_nan_points); PCL keeps
  // organised clouds organised, NaN pixels included.
  const open3d::io::ReadPointCloudOption o3d_option("auto", true, false, false);

  std::size_t ours_n = 0, pcl_n = 0, pcl_finite = 0, o3d_n = 0;
  auto read_ours = [&](const fs::path& path) { ours_n = read_cloud(path).size(); };
  auto read_open3d = [&](const fs::path& path) {
    open3d::geometry::PointCloud cloud;
    if (!open3d::io::ReadPointCloud(path.string(), cloud, o3d_option))
      throw IoError(path.string() + ": Open3D could not read it");
    o3d_n = cloud.points_.size();
  };
  auto count_finite = [](const auto& cloud) {
    std::size_t n = 0;
    for (const auto& p : cloud.points) n += std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z);
    return n;
  };

  {
    const std::string name = "read ASCII PLY " + in.ply.filename().string();
    Row pcl_row{name, "pcl::io::loadPLYFile<PointXYZ>"};
    std::tie(pcl_row.ours, pcl_row.theirs) = measure_pair(
        options, [&] { read_ours(in.ply); },
        [&] {
          pcl::PointCloud<pcl::PointXYZ> cloud;
          if (pcl::io::loadPLYFile(in.ply.string(), cloud) < 0)
            throw IoError(in.ply.string() + ": PCL could not read it");
          pcl_n = cloud.size();
        });
    Row o3d_row{name, "open3d::io::ReadPointCloud"};
    std::tie(o3d_row.ours, o3d_row.theirs) =
        measure_pair(options, [&] { read_ours(in.ply); }, [&] { read_open3d(in.ply); });
    {
      pcl::PointCloud<pcl::PointXYZ> cloud;
      pcl::io::loadPLYFile(in.ply.string(), cloud);
      pcl_finite = count_finite(cloud);
    }
    report.rows.push_back(pcl_row);
    report.rows.push_back(o3d_row);
    report.note(in.ply.filename().string() + " (" + size_text(in.ply) + "): points read: ours " +
                std::to_string(ours_n) + ", PCL " + std::to_string(pcl_n) + " (" +
                std::to_string(pcl_finite) + " finite), Open3D " + std::to_string(o3d_n));
  }
  {
    const std::string name = "read binary_compressed PCD " + in.pcd.filename().string();
    Row pcl_row{name, "pcl::io::loadPCDFile<PointXYZRGB>"};
    std::tie(pcl_row.ours, pcl_row.theirs) = measure_pair(
        options, [&] { read_ours(in.pcd); },
        [&] {
          pcl::PointCloud<pcl::PointXYZRGB> cloud;
          if (pcl::io::loadPCDFile(in.pcd.string(), cloud) < 0)
            throw IoError(in.pcd.string() + ": PCL could not read it");
          pcl_n = cloud.size();
        });
    Row o3d_row{name, "open3d::io::ReadPointCloud"};
    std::tie(o3d_row.ours, o3d_row.theirs) =
        measure_pair(options, [&] { read_ours(in.pcd); }, [&] { read_open3d(in.pcd); });
    {
      pcl::PointCloud<pcl::PointXYZRGB> cloud;
      pcl::io::loadPCDFile(in.pcd.string(), cloud);
      pcl_finite = count_finite(cloud);
    }
    report.rows.push_back(pcl_row);
    report.rows.push_back(o3d_row);
    report.note(in.pcd.filename().string() + " (" + size_text(in.pcd) + "): points read: ours " +
                std::to_string(ours_n) + ", PCL " + std::to_string(pcl_n) + " (" +
                std::to_string(pcl_finite) + " finite), Open3D " + std::to_string(o3d_n));
  }
  report.note("I/O: files are in the page cache after the warm-up, so this times parsing; "
              "ours and Open3D drop NaN points (Open3D with remove_nan_points), PCL keeps "
              "organised clouds with their NaN points");
}

}  // namespace station::bench
