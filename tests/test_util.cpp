#include "test_util.h"

#include <cmath>

#include <algorithm>
#include <atomic>
#include <map>
#include <random>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>

namespace station::test {

Mesh icosphere(int level, double radius, const Vec3f& center) {
  const float t = (1.f + std::sqrt(5.f)) / 2.f;
  std::vector<Vec3f> v = {{-1, t, 0}, {1, t, 0},  {-1, -t, 0}, {1, -t, 0},
                          {0, -1, t}, {0, 1, t},  {0, -1, -t}, {0, 1, -t},
                          {t, 0, -1}, {t, 0, 1},  {-t, 0, -1}, {-t, 0, 1}};
  for (auto& p : v) p.normalize();
  std::vector<Face> f = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                         {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                         {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                         {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
  for (int l = 0; l < level; ++l) {
    std::map<std::pair<int, int>, int> mid;
    auto midpoint = [&](int a, int b) {
      auto key = std::minmax(a, b);
      auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      v.push_back((v[a] + v[b]).normalized());
      mid[key] = int(v.size()) - 1;
      return int(v.size()) - 1;
    };
    std::vector<Face> nf;
    for (const Face& fc : f) {
      int a = midpoint(fc[0], fc[1]), b = midpoint(fc[1], fc[2]), c = midpoint(fc[2], fc[0]);
      nf.push_back({fc[0], a, c});
      nf.push_back({fc[1], b, a});
      nf.push_back({fc[2], c, b});
      nf.push_back({a, b, c});
    }
    f.swap(nf);
  }
  Mesh m;
  for (auto& p : v) m.vertices.push_back(center + float(radius) * p);
  m.faces = f;
  return m;
}

Mesh box(const Vec3f& lo, const Vec3f& hi) {
  Mesh m;
  for (int i = 0; i < 8; ++i)
    m.vertices.push_back({(i & 1) ? hi.x() : lo.x(), (i & 2) ? hi.y() : lo.y(),
                          (i & 4) ? hi.z() : lo.z()});
  // Outward-facing quads split into triangles.
  const int quads[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                           {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (auto& q : quads) {
    m.faces.push_back({q[0], q[1], q[2]});
    m.faces.push_back({q[0], q[2], q[3]});
  }
  return m;
}

TempDir::TempDir(const std::string& tag) {
  static std::atomic<int> counter{0};
  std::random_device rd;
  path_ = std::filesystem::temp_directory_path() /
          (tag + "-" + std::to_string(::getpid()) + "-" + std::to_string(counter++) + "-" +
           std::to_string(rd() % 100000));
  std::filesystem::create_directories(path_);
}

TempDir::~TempDir() {
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

std::filesystem::path source_dir() { return STATION_SOURCE_DIR; }

Cloud fibonacci_sphere(int n, double r) {
  Cloud c;
  const double golden = M_PI * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n, rr = std::sqrt(1 - z * z);
    const Vec3d d(rr * std::cos(golden * i), rr * std::sin(golden * i), z);
    c.points.push_back((r * d).cast<float>());
    c.normals.push_back(d.cast<float>());
  }
  return c;
}

int open_edges(const Mesh& m) {
  std::map<std::pair<int, int>, int> uses;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) ++uses[std::minmax(f[t], f[(t + 1) % 3])];
  int bad = 0;
  for (const auto& [e, n] : uses) bad += n != 2;
  return bad;
}

CommandResult run_command(const std::string& command) {
  const std::string cmd = command + " 2>&1";
  CommandResult r;
  FILE* p = ::popen(cmd.c_str(), "r");
  if (!p) return r;
  std::array<char, 4096> buf;
  std::size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int status = ::pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

}  // namespace station::test
