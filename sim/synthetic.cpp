// "sim:synthetic": the ray-casting range + colour camera of the virtual bench.
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>

#include "core/error.h"
#include "drivers/options.h"
#include "sim/bench.h"

namespace station {

namespace sim {

double parse_double_option(const std::string& uri, const std::string& key, const std::string& value) {
  double x = 0;
  require_option(parse_number(value, x), uri, key, value, "not a finite number");
  return x;
}

long long parse_int_option(const std::string& uri, const std::string& key, const std::string& value) {
  const char* s = value.c_str();
  char* end = nullptr;
  errno = 0;
  const long long x = std::strtoll(s, &end, 10);
  require_option(!value.empty() && end == s + value.size() && errno != ERANGE, uri, key, value,
                 "not an integer");
  return x;
}

bool parse_bool_option(const std::string& uri, const std::string& key, const std::string& value) {
  std::string v;
  for (char c : value) v.push_back(char(std::tolower(static_cast<unsigned char>(c))));
  if (v == "1" || v == "true" || v == "yes" || v == "on") return true;
  if (v == "0" || v == "false" || v == "no" || v == "off") return false;
  require_option(false, uri, key, value, "not a boolean (1/0, true/false, yes/no, on/off)");
  return false;
}

void require_option(bool ok, const std::string& uri, const std::string& key,
                    const std::string& value, const std::string& why) {
  if (!ok) throw DeviceError(uri + ": option '" + key + "': '" + value + "': " + why);
}

void unknown_option(const std::string& uri, const std::string& key, const std::string& known) {
  throw DeviceError(uri + ": unknown option '" + key + "' (known: " + known + ")");
}

}  // namespace sim

SyntheticParams synthetic_params_from_options(const DeviceOptions& options,
                                              const std::string& uri) {
  using namespace sim;
  SyntheticParams p;
  static const char* kKnown =
      "mesh, scale, center, width, height, fov_deg, distance, elevation_deg, target_height, "
      "noise, noise_quadratic, dropout, color_noise, table_radius, max_range, seed, color";
  for (const auto& [key, value] : options) {
    auto num = [&] { return parse_double_option(uri, key, value); };
    auto check = [&](bool ok, const char* why) { require_option(ok, uri, key, value, why); };
    if (key == "mesh") {
      p.mesh = value;
    } else if (key == "scale") {
      p.scale = num();
      check(p.scale > 0, "must be > 0");
    } else if (key == "center") {
      p.center = parse_bool_option(uri, key, value);
    } else if (key == "width" || key == "height") {
      const long long n = parse_int_option(uri, key, value);
      check(n >= 1 && n <= 16384, "must be in [1, 16384]");
      (key == "width" ? p.width : p.height) = int(n);
    } else if (key == "fov_deg") {
      p.fov_deg = num();
      check(p.fov_deg > 0 && p.fov_deg < 180, "must be in (0, 180)");
    } else if (key == "distance") {
      p.distance = num();
      check(p.distance > 0, "must be > 0");
    } else if (key == "elevation_deg") {
      p.elevation_deg = num();
      check(p.elevation_deg > -90 && p.elevation_deg < 90, "must be in (-90, 90)");
    } else if (key == "target_height") {
      p.target_height = num();
    } else if (key == "noise") {
      p.noise = num();
      check(p.noise >= 0, "must be >= 0");
    } else if (key == "noise_quadratic") {
      p.noise_quadratic = num();
      check(p.noise_quadratic >= 0, "must be >= 0");
    } else if (key == "dropout") {
      p.dropout = num();
      check(p.dropout >= 0 && p.dropout <= 1, "must be in [0, 1]");
    } else if (key == "color_noise") {
      p.colour_noise = num();
      check(p.colour_noise >= 0, "must be >= 0");
    } else if (key == "table_radius") {
      p.table_radius = num();
      check(p.table_radius >= 0, "must be >= 0");
    } else if (key == "max_range") {
      p.max_range = num();
      check(p.max_range > 0, "must be > 0");
    } else if (key == "seed") {
      const long long n = parse_int_option(uri, key, value);
      check(n >= 0 && n <= (long long)std::numeric_limits<unsigned>::max(),
            "must be in [0, 4294967295]");
      p.seed = unsigned(n);
    } else if (key == "color") {
      p.colour = parse_bool_option(uri, key, value);
    } else {
      unknown_option(uri, key, kKnown);
    }
  }
  return p;
}

namespace sim {
namespace {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

class SyntheticScanner final : public Scanner {
 public:
  SyntheticScanner(DeviceUri uri, std::shared_ptr<Bench> bench)
      : uri_(std::move(uri)),
        options_(uri_.options),
        params_(synthetic_params_from_options(options_, uri_.text)),
        bench_(std::move(bench)) {}

  void open() override {
    scene_ = load_scene(params_);
    frame_index_ = 0;
  }

  void close() override { scene_.reset(); }

  void configure(const DeviceOptions& options) override {
    DeviceOptions merged = options_;
    for (const auto& [k, v] : options) merged[k] = v;
    const SyntheticParams next = synthetic_params_from_options(merged, uri_.text);
    const bool placement_changed =
        next.mesh != params_.mesh || next.scale != params_.scale || next.center != params_.center;
    if (scene_) {
      // Load before committing, so a bad new mesh leaves the scanner as it was.
      if (placement_changed)
        scene_ = load_scene(next);
      else
        scene_->set_params(next);
    }
    options_ = std::move(merged);
    params_ = next;
  }

  ScannerCapabilities capabilities() const override {
    ScannerCapabilities caps;
    caps.depth = true;
    caps.colour = params_.colour;
    // Intrinsics depend on the options only. The axis depends on where the camera
    // aims: known up front with an explicit target_height, else (mesh mid-height)
    // once the mesh is loaded by open().
    caps.intrinsics = synthetic_intrinsics(params_);
    if (scene_)
      caps.axis = scene_->axis();
    else if (params_.target_height >= 0)
      caps.axis = axis_in_camera(camera_in_table(params_, params_.target_height));
    return caps;
  }

  void resume_at(std::uint64_t view) override { frame_index_ = view; }

  Frame grab() override {
    if (!scene_) throw DeviceError(uri_.text + ": grab() before open()");
    Frame f = scene_->render(bench_->angle_deg(), frame_index_++);
    f.timestamp = now_seconds();
    return f;
  }

  std::string uri() const override { return uri_.text; }

 private:
  std::unique_ptr<Scene> load_scene(const SyntheticParams& params) const {
    if (params.mesh.empty())
      throw DeviceError(uri_.text + ": no mesh given (option 'mesh=FILE')");
    const fs::path path = params.mesh;
    std::error_code ec;
    if (!fs::is_regular_file(path, ec))
      throw DeviceError(uri_.text + ": mesh " + path.string() + ": no such file");
    try {
      TexturedMesh mesh = read_textured_mesh(path);
      // Scanned without it, every view would come out uncoloured, said nowhere.
      if (!mesh.material_problem.empty())
        throw DeviceError(uri_.text + ": mesh " + path.string() + ": " + mesh.material_problem +
                          " (restore it, or remove the mtllib line to scan the mesh uncoloured)");
      Texture texture;
      if (!mesh.texture.empty() && !mesh.corner_uv.empty()) texture = load_texture(mesh.texture);
      return std::make_unique<Scene>(std::move(mesh), std::move(texture), params);
    } catch (const InvalidInput& e) {  // unusable geometry (no faces, bad indices)
      throw DeviceError(uri_.text + ": mesh " + path.string() + ": " + e.what());
    } catch (const DeviceError&) {
      throw;
    } catch (const Error& e) {
      // IoError/FormatError already name the file; keep the device URI in front
      // so the CLI says which device failed.
      throw DeviceError(uri_.text + ": " + e.what());
    }
  }

  DeviceUri uri_;
  DeviceOptions options_;
  SyntheticParams params_;
  std::shared_ptr<Bench> bench_;
  std::unique_ptr<Scene> scene_;
  std::uint64_t frame_index_ = 0;
};

}  // namespace

std::unique_ptr<Scanner> make_synthetic_scanner(const DeviceUri& uri, DeviceContext& context) {
  return std::make_unique<SyntheticScanner>(uri, bench_of(context));
}

}  // namespace sim
}  // namespace station
