// Ray casting one 640x480 depth view: our TriangleBvh (and the simulator's
// Scene::render around it) against Embree 3 driven as Open3D's RaycastingScene
// drives it, and against RaycastingScene itself where that works, on the same
// rays, for the bundled mustard bottle and a ~100k-triangle icosphere.
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>
#include <tuple>
#include <utility>

#include <embree3/rtcore.h>
#include <open3d/Open3DConfig.h>
#include <open3d/core/Tensor.h>
#include <open3d/t/geometry/RaycastingScene.h>

#include "core/bvh.h"
#include "core/io.h"
#include "core/texture.h"
#include "harness.h"
#include "sim/bench.h"

namespace station::bench {

namespace {

namespace o3c = open3d::core;
using open3d::t::geometry::RaycastingScene;

/// Geodesic sphere: the icosahedron with every face split into frequency^2
/// triangles, all vertices pushed onto the sphere (20 * frequency^2 faces,
/// vertices shared along edges so the surface is watertight). Faces are
/// counter-clockwise seen from outside.
Mesh icosphere(int frequency, float radius) {
  const float g = (1.f + std::sqrt(5.f)) / 2.f;
  std::vector<Vec3f> corners;
  for (float s1 : {-1.f, 1.f})
    for (float s2 : {-g, g}) {
      corners.emplace_back(0.f, s1, s2);
      corners.emplace_back(s1, s2, 0.f);
      corners.emplace_back(s2, 0.f, s1);
    }
  // The 20 faces are the corner triples at mutual distance 2 (the edge length).
  std::vector<Face> base;
  auto adjacent = [&](int a, int b) { return std::abs((corners[a] - corners[b]).norm() - 2.f) < 1e-3f; };
  for (int a = 0; a < 12; ++a)
    for (int b = a + 1; b < 12; ++b)
      for (int c = b + 1; c < 12; ++c)
        if (adjacent(a, b) && adjacent(b, c) && adjacent(a, c)) {
          const Vec3f n = (corners[b] - corners[a]).cross(corners[c] - corners[a]);
          base.push_back(n.dot(corners[a]) > 0 ? Face(a, b, c) : Face(a, c, b));
        }

  Mesh mesh;
  for (const Vec3f& c : corners) mesh.vertices.push_back(radius * c.normalized());
  const int n = frequency;
  // Edge points are keyed by (lower corner, higher corner, steps from the lower
  // one) so both faces of an edge get the same vertex.
  std::map<std::tuple<int, int, int>, int> edge_points;
  auto on_sphere = [&](const Vec3f& p) {
    mesh.vertices.push_back(radius * p.normalized());
    return int(mesh.vertices.size()) - 1;
  };
  auto edge_point = [&](int p, int q, int steps_from_p) {
    if (steps_from_p == 0) return p;
    if (steps_from_p == n) return q;
    const auto key = p < q ? std::make_tuple(p, q, steps_from_p) : std::make_tuple(q, p, n - steps_from_p);
    const auto found = edge_points.find(key);
    if (found != edge_points.end()) return found->second;
    const auto [lo, hi, s] = key;
    const int id = on_sphere(float(n - s) * corners[lo] + float(s) * corners[hi]);
    edge_points.emplace(key, id);
    return id;
  };
  for (const Face& f : base) {
    // Lattice point (i, j) = a + i/n (b - a) + j/n (c - a).
    std::vector<int> lattice(std::size_t(n + 1) * (n + 1), -1);
    auto at = [&](int i, int j) -> int& { return lattice[std::size_t(j) * (n + 1) + i]; };
    for (int j = 0; j <= n; ++j)
      for (int i = 0; i + j <= n; ++i) {
        const int k = n - i - j;
        if (j == 0) at(i, j) = edge_point(f[0], f[1], i);
        else if (i == 0) at(i, j) = edge_point(f[0], f[2], j);
        else if (k == 0) at(i, j) = edge_point(f[1], f[2], j);
        else at(i, j) = on_sphere(float(k) * corners[f[0]] + float(i) * corners[f[1]] + float(j) * corners[f[2]]);
      }
    for (int j = 0; j < n; ++j)
      for (int i = 0; i + j < n; ++i) {
        mesh.faces.emplace_back(at(i, j), at(i + 1, j), at(i, j + 1));
        if (i + j < n - 1) mesh.faces.emplace_back(at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
      }
  }
  return mesh;
}

/// The rays of one view of `scene` at table angle `angle_deg`, in the placed
/// frame (where the BVH lives), as the simulator casts them: t = depth.
std::vector<Ray> view_rays(const sim::Scene& scene, double angle_deg) {
  const Intrinsics k = scene.intrinsics();
  const Eigen::Matrix4d placed_from_camera = sim::rotate_z_deg(-angle_deg) * scene.table_from_camera();
  const Eigen::Matrix3d rot = placed_from_camera.topLeftCorner<3, 3>();
  const Vec3d origin = placed_from_camera.topRightCorner<3, 1>();
  std::vector<Ray> rays;
  rays.reserve(std::size_t(k.width) * k.height);
  for (int row = 0; row < k.height; ++row)
    for (int col = 0; col < k.width; ++col)
      rays.push_back({origin, rot * Vec3d((col - k.cx) / k.fx, (row - k.cy) / k.fy, 1.0)});
  return rays;
}

/// The same rays as Embree and Open3D take them: N x (origin, direction) floats.
std::vector<float> flat(const std::vector<Ray>& rays) {
  std::vector<float> out;
  out.reserve(rays.size() * 6);
  for (const Ray& r : rays)
    for (const Vec3d* v : {&r.origin, &r.direction})
      for (int c = 0; c < 3; ++c) out.push_back(float((*v)[c]));
  return out;
}

/// Depth per ray (inf on a miss) with `threads` TBB workers.
void cast_ours(const TriangleBvh& bvh, const std::vector<Ray>& rays, int threads,
               std::vector<float>& depth) {
  depth.assign(rays.size(), std::numeric_limits<float>::infinity());
  tbb::task_arena arena(threads);
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, rays.size(), 1024), [&](const auto& range) {
      for (std::size_t i = range.begin(); i != range.end(); ++i)
        if (const auto hit = bvh.intersect(rays[i])) depth[i] = float(hit->t);
    });
  });
}

std::unique_ptr<RaycastingScene> open3d_scene(const Mesh& mesh, int threads) {
  std::vector<float> vertices;
  vertices.reserve(mesh.vertices.size() * 3);
  for (const Vec3f& v : mesh.vertices) vertices.insert(vertices.end(), {v.x(), v.y(), v.z()});
  std::vector<std::uint32_t> faces;
  faces.reserve(mesh.faces.size() * 3);
  for (const Face& f : mesh.faces)
    faces.insert(faces.end(), {std::uint32_t(f[0]), std::uint32_t(f[1]), std::uint32_t(f[2])});
  auto scene = std::make_unique<RaycastingScene>(threads);
  scene->AddTriangles(o3c::Tensor(std::move(vertices), {std::int64_t(mesh.vertices.size()), 3}),
                      o3c::Tensor(std::move(faces), {std::int64_t(mesh.faces.size()), 3}));
  return scene;
}

/// Embree 3 driven as Open3D 0.16's RaycastingScene drives it (device with
/// "threads=N", scene flags robust + context filter, one triangle geometry;
/// rays in TBB batches of rtcIntersect1M) except for the ray mask: all bits set, so a ray-mask build of
/// Embree (Debian's) sees the geometry.
class EmbreeScene {
 public:
  EmbreeScene(const Mesh& mesh, int threads) {
    const std::string config = "threads=" + std::to_string(threads);
    device_ = rtcNewDevice(config.c_str());
    if (!device_) throw std::runtime_error("embree: rtcNewDevice failed");
    scene_ = rtcNewScene(device_);
    rtcSetSceneFlags(scene_, RTC_SCENE_FLAG_ROBUST | RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION);
    RTCGeometry geometry = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0,
                                                          RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                                          mesh.vertices.size()));
    for (std::size_t i = 0; i < mesh.vertices.size(); ++i)
      for (int c = 0; c < 3; ++c) v[3 * i + c] = mesh.vertices[i][c];
    auto* f = static_cast<unsigned*>(rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_INDEX, 0,
                                                             RTC_FORMAT_UINT3, 3 * sizeof(unsigned),
                                                             mesh.faces.size()));
    for (std::size_t i = 0; i < mesh.faces.size(); ++i)
      for (int c = 0; c < 3; ++c) f[3 * i + c] = unsigned(mesh.faces[i][c]);
    rtcCommitGeometry(geometry);
    rtcAttachGeometry(scene_, geometry);
    rtcReleaseGeometry(geometry);
    rtcCommitScene(scene_);
  }
  ~EmbreeScene() {
    rtcReleaseScene(scene_);
    rtcReleaseDevice(device_);
  }
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;

  /// rays: N x (origin, direction) floats; depth: t or inf per ray.
  void cast(const std::vector<float>& rays, int threads, std::vector<float>& depth) const {
    const std::size_t n = rays.size() / 6;
    depth.assign(n, std::numeric_limits<float>::infinity());
    tbb::task_arena arena(threads);
    arena.execute([&] {
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const auto& range) {
        RTCIntersectContext context;
        rtcInitIntersectContext(&context);
        std::vector<RTCRayHit> hits(range.size());
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
          RTCRayHit& h = hits[i - range.begin()];
          const float* r = &rays[6 * i];
          h.ray.org_x = r[0], h.ray.org_y = r[1], h.ray.org_z = r[2];
          h.ray.dir_x = r[3], h.ray.dir_y = r[4], h.ray.dir_z = r[5];
          h.ray.tnear = 0;
          h.ray.tfar = std::numeric_limits<float>::infinity();
          h.ray.time = 0;
          h.ray.mask = ~0u;
          h.ray.id = unsigned(i - range.begin());
          h.ray.flags = 0;
          h.hit.geomID = RTC_INVALID_GEOMETRY_ID;
          h.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
        }
        rtcIntersect1M(scene_, &context, hits.data(), unsigned(hits.size()), sizeof(RTCRayHit));
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
          const RTCRayHit& h = hits[i - range.begin()];
          if (h.hit.geomID != RTC_INVALID_GEOMETRY_ID) depth[i] = h.ray.tfar;
        }
      });
    });
  }

 private:
  RTCDevice device_ = nullptr;
  RTCScene scene_ = nullptr;
};

struct Agreement {
  std::size_t ours = 0, theirs = 0, both = 0;
  double max_diff = 0;
  std::string text(const std::string& who) const {
    const std::size_t either = ours + theirs - both;
    return "hits ours " + std::to_string(ours) + ", " + who + " " + std::to_string(theirs) +
           ", both " + std::to_string(both) + " (" +
           format_fixed(either ? 100.0 * double(both) / double(either) : 100.0, 3) +
           " % of the rays either hits), max depth difference where both hit " +
           format_fixed(max_diff * 1e6, 2) + " um";
  }
};

Agreement compare(const std::vector<float>& ours, const float* theirs) {
  Agreement a;
  for (std::size_t i = 0; i < ours.size(); ++i) {
    const bool x = std::isfinite(ours[i]), y = std::isfinite(theirs[i]);
    a.ours += x;
    a.theirs += y;
    if (x && y) {
      ++a.both;
      a.max_diff = std::max(a.max_diff, double(std::abs(ours[i] - theirs[i])));
    }
  }
  return a;
}

void bench_mesh(const Options& options, Report& report, const std::string& label,
                sim::Scene& scene) {
  const Mesh& mesh = scene.placed_mesh();
  const int threads = options.threads;
  const std::vector<Ray> rays = view_rays(scene, 30.0);
  const std::vector<float> flat_rays = flat(rays);
  const std::string what = label + " (" + std::to_string(mesh.faces.size()) + " tri)";

  Row build{what + ": build BVH", "Embree 3 scene commit"};
  std::tie(build.ours, build.theirs) = measure_pair(
      options, [&] { TriangleBvh bvh(mesh); }, [&] { EmbreeScene s(mesh, threads); });
  report.rows.push_back(build);

  const TriangleBvh bvh(mesh);
  const EmbreeScene embree(mesh, threads);
  std::vector<float> ours_depth, embree_depth;
  Row cast{what + ": cast 640x480 view", "Embree rtcIntersect1M (as Open3D)"};
  std::tie(cast.ours, cast.theirs) =
      measure_pair(options, [&] { cast_ours(bvh, rays, threads, ours_depth); },
                   [&] { embree.cast(flat_rays, threads, embree_depth); });
  report.rows.push_back(cast);

  if (threads > 1) {
    Row single{what + ": cast 640x480, 1 thread", "Embree rtcIntersect1M (as Open3D)"};
    std::vector<float> scratch;
    std::tie(single.ours, single.theirs) =
        measure_pair(options, [&] { cast_ours(bvh, rays, 1, scratch); },
                     [&] { embree.cast(flat_rays, 1, scratch); });
    report.rows.push_back(single);
  }

  Row render{what + ": sim Scene::render view", "Embree cast (depth only)"};
  render.ours = measure(options, [&] {
    tbb::task_arena arena(threads);
    arena.execute([&] { scene.render(30.0, 0); });
  });
  render.theirs = cast.theirs;
  report.rows.push_back(render);
  report.note(what + ", " + std::to_string(rays.size()) + " rays, vs Embree: " +
              compare(ours_depth, embree_depth.data()).text("Embree"));

  // Open3D's own RaycastingScene, when its build works: timed like Embree above.
  auto o3d = open3d_scene(mesh, threads);
  const o3c::Tensor o3d_rays(std::vector<float>(flat_rays), {std::int64_t(rays.size()), 6});
  const o3c::Tensor probe = o3d->CastRays(o3d_rays, threads)["t_hit"].Contiguous();
  const Agreement with_open3d = compare(ours_depth, probe.GetDataPtr<float>());
  if (with_open3d.theirs == 0 && with_open3d.ours > 0) {
    report.note(what + ": Open3D " OPEN3D_VERSION " RaycastingScene::CastRays hit nothing (" +
                std::to_string(with_open3d.ours) + " rays hit for us and Embree): this build "
                "sets ray.mask = 0 and Debian's Embree is built with ray masks, so every ray "
                "misses; not timed");
    return;
  }
  Row open3d_build{what + ": build BVH", "Open3D RaycastingScene (commit)"};
  const o3c::Tensor one_ray = o3d_rays.Slice(0, 0, 1);  // Open3D commits on the first query
  std::tie(open3d_build.ours, open3d_build.theirs) = measure_pair(
      options, [&] { TriangleBvh bvh(mesh); },
      [&] { open3d_scene(mesh, threads)->CastRays(one_ray, threads); });
  Row open3d_cast{what + ": cast 640x480 view", "Open3D RaycastingScene::CastRays"};
  std::vector<float> scratch;
  std::tie(open3d_cast.ours, open3d_cast.theirs) =
      measure_pair(options, [&] { cast_ours(bvh, rays, threads, scratch); },
                   [&] { o3d->CastRays(o3d_rays, threads); });
  report.rows.push_back(open3d_build);
  report.rows.push_back(open3d_cast);
  report.note(what + " vs Open3D: " + with_open3d.text("Open3D"));
}

}  // namespace

void run_raycast_cases(const Options& options, Report& report) {
  SyntheticParams params;  // the default profile's camera (config/default.yaml)
  params.dropout = 0.01;
  params.colour_noise = 2;

  {
    const fs::path obj = options.source_dir / "data" / "mustard_bottle" / "textured.obj";
    TexturedMesh textured = read_textured_mesh(obj);
    Texture texture = textured.texture.empty() ? Texture{} : load_texture(textured.texture);
    params.mesh = obj.string();
    sim::Scene scene(std::move(textured), std::move(texture), params);
    bench_mesh(options, report, "mustard", scene);
  }
  {
    // Frequency 71: 20 * 71^2 = 100,820 triangles, the "100k-triangle mesh".
    TexturedMesh sphere;
    sphere.mesh = icosphere(71, 0.08f);
    params.mesh.clear();
    params.center = true;
    sim::Scene scene(std::move(sphere), Texture{}, params);
    bench_mesh(options, report, "icosphere", scene);
  }
  report.note("ray casting: sim camera of config/default.yaml (640x480, 50 deg, 0.45 m, 20 deg "
              "elevation) at table angle 30 deg; ours intersects in double precision, Embree in "
              "float (its AVX-512/AVX2 kernels); Scene::render adds the turntable disk, "
              "texture/colour lookup, noise and dropouts, its anchor column repeats the Embree "
              "cast time");
}

}  // namespace station::bench
