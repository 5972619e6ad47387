#include "station/serve.h"

#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <arpa/inet.h>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <fstream>
#include <mutex>
#include <new>
#include <optional>
#include <sstream>
#include <unistd.h>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/error.h"
#include "core/camera.h"
#include "core/io.h"
#include "drivers/registry.h"
#include "station/commands.h"
#include "station/config.h"
#include "station/jobs.h"
#include "station/pipeline.h"

// The only translation unit that includes cpp-httplib (slow to compile, and its
// Debian build needs its pkg-config flags). After Eigen: it brings <resolv.h>,
// whose _res macro breaks Eigen's headers.
#include <httplib.h>
#include <nlohmann/json.hpp>

#ifndef STATION_SOURCE_DIR
#define STATION_SOURCE_DIR "."
#endif
#ifndef STATION_THREE_DIR
#define STATION_THREE_DIR "/usr/share/javascript/three"
#endif
#ifndef STATION_VERSION
#define STATION_VERSION "dev"
#endif

namespace station {

namespace fs = std::filesystem;
using Json = nlohmann::json;

bool is_loopback_address(const std::string& address) {
  if (address == "localhost" || address == "::1") return true;
  in_addr a{};
  if (::inet_pton(AF_INET, address.c_str(), &a) == 1) return (ntohl(a.s_addr) >> 24) == 127;
  return false;
}

std::string read_token_file(const fs::path& file) {
  std::istringstream in(read_file_bytes(file));  // (a folder, a device or a FIFO: named)
  std::string line;
  std::getline(in, line);
  const auto b = line.find_first_not_of(" \t\r\n");
  const auto e = line.find_last_not_of(" \t\r\n");
  const std::string token = b == std::string::npos ? "" : line.substr(b, e - b + 1);
  if (token.size() < 16)
    throw InvalidInput(file.string() + ": the token must be at least 16 characters on the first line");
  return token;
}

namespace {

/// An answer other than 200, with its one-line message.
class HttpError : public Error {
 public:
  HttpError(int status, const std::string& what) : Error(what), status(status) {}
  int status;
};

/// Constant-time comparison (the time does not depend on where they differ).
bool same_secret(const std::string& a, const std::string& b) {
  volatile unsigned char diff = static_cast<unsigned char>(a.size() != b.size());
  const std::size_t n = std::max(a.size(), b.size());
  for (std::size_t i = 0; i < n; ++i) {
    const unsigned char x = i < a.size() ? static_cast<unsigned char>(a[i]) : 0;
    const unsigned char y = i < b.size() ? static_cast<unsigned char>(b[i]) : 0;
    diff = static_cast<unsigned char>(diff | (x ^ y));
  }
  return diff == 0;
}

void send_json(httplib::Response& res, int status, const Json& j) {
  res.status = status;
  res.set_header("Cache-Control", "no-store");
  res.set_content(j.dump(), "application/json");
}

void send_error(httplib::Response& res, int status, const std::string& message) {
  send_json(res, status, Json{{"error", message}});
}

std::string cookie(const httplib::Request& req, const std::string& name) {
  const std::string all = req.get_header_value("Cookie");
  std::size_t pos = 0;
  while (pos < all.size()) {
    std::size_t end = all.find(';', pos);
    if (end == std::string::npos) end = all.size();
    std::string item = all.substr(pos, end - pos);
    const auto b = item.find_first_not_of(' ');
    if (b != std::string::npos) item = item.substr(b);
    if (item.rfind(name + "=", 0) == 0) return item.substr(name.size() + 1);
    pos = end + 1;
  }
  return {};
}

/// The host part of a Host header ("127.0.0.1:8080" -> "127.0.0.1", "[::1]:80" -> "::1").
std::string host_name(const std::string& host) {
  if (!host.empty() && host[0] == '[') {
    const auto e = host.find(']');
    return e == std::string::npos ? host : host.substr(1, e - 1);
  }
  return host.substr(0, host.find(':'));
}

/// The request's JSON object body (HttpError 400/415 when it is not one).
Json json_body(const httplib::Request& req) {
  if (req.body.empty()) return Json::object();
  Json j = Json::parse(req.body, nullptr, false);
  if (j.is_discarded()) throw HttpError(400, "request body: not valid JSON");
  if (!j.is_object()) throw HttpError(400, "request body: expected a JSON object");
  return j;
}

std::string get_string(const Json& j, const char* key) {
  if (!j.contains(key) || j[key].is_null()) return {};
  if (!j[key].is_string()) throw HttpError(400, std::string("request body: ") + key + ": expected a string");
  return j[key].get<std::string>();
}
bool get_bool(const Json& j, const char* key, bool fallback) {
  if (!j.contains(key) || j[key].is_null()) return fallback;
  if (!j[key].is_boolean()) throw HttpError(400, std::string("request body: ") + key + ": expected true or false");
  return j[key].get<bool>();
}
int get_int(const Json& j, const char* key) {
  if (!j.contains(key) || j[key].is_null()) return 0;
  if (!j[key].is_number_integer()) throw HttpError(400, std::string("request body: ") + key + ": expected an integer");
  const long long v = j[key].get<long long>();
  if (v < -1000000 || v > 1000000) throw HttpError(400, std::string("request body: ") + key + ": out of range");
  return int(v);
}

/// The handler with the station's errors as JSON answers.
template <class F>
httplib::Server::Handler api(F f) {
  return [f](const httplib::Request& req, httplib::Response& res) {
    try {
      f(req, res);
    } catch (const HttpError& e) {
      send_error(res, e.status, e.what());
    } catch (const NotFound& e) {
      send_error(res, 404, e.what());
    } catch (const JobBusy& e) {
      send_error(res, 409, e.what());
    } catch (const InvalidInput& e) {
      send_error(res, 400, e.what());
    } catch (const DeviceError& e) {
      send_error(res, 503, e.what());
    } catch (const Error& e) {
      send_error(res, 500, e.what());
    } catch (const Json::exception& e) {
      send_error(res, 400, std::string("request: ") + e.what());
    } catch (const std::bad_alloc&) {
      send_error(res, 500, "out of memory");
    } catch (const std::exception& e) {
      send_error(res, 500, std::string("internal error: ") + e.what());
    }
  };
}

Json job_json(const JobInfo& i) {
  Json j = {{"id", i.id},           {"kind", i.kind},       {"session", i.session},
            {"state", to_string(i.state)}, {"seconds", i.seconds}, {"events", i.events}};
  if (!i.device.empty()) j["device"] = i.device;
  if (!i.error.empty()) j["error"] = i.error;
  return j;
}

const char* content_type(const fs::path& p) {
  const std::string e = p.extension().string();
  if (e == ".png") return "image/png";
  if (e == ".jpg" || e == ".jpeg") return "image/jpeg";
  if (e == ".html") return "text/html; charset=utf-8";
  if (e == ".yaml" || e == ".txt" || e == ".obj" || e == ".mtl") return "text/plain; charset=utf-8";
  if (e == ".json") return "application/json";
  return "application/octet-stream";
}

/// Depth as a colour map (near red, far blue; no return black) and the colour
/// image, side by side, as PNG bytes.
std::string preview_png(const Frame& f) {
  std::vector<cv::Mat> panels;
  if (f.has_depth() && f.intrinsics.width > 0 && f.intrinsics.height > 0 &&
      f.depth.size() == std::size_t(f.intrinsics.width) * std::size_t(f.intrinsics.height)) {
    cv::Mat d(f.intrinsics.height, f.intrinsics.width, CV_32F, const_cast<float*>(f.depth.data()));
    cv::Mat valid = (d > 0) & (d == d);
    double lo = 0, hi = 0;
    cv::minMaxLoc(d, &lo, &hi, nullptr, nullptr, valid);
    cv::Mat grey;
    d.convertTo(grey, CV_8U, hi > lo ? -255.0 / (hi - lo) : 0, hi > lo ? 255.0 * hi / (hi - lo) : 0);
    cv::Mat coloured;
    cv::applyColorMap(grey, coloured, cv::COLORMAP_TURBO);
    coloured.setTo(cv::Scalar(0, 0, 0), ~valid);
    panels.push_back(coloured);
  }
  const Intrinsics& ci = f.colour_intrinsics.width > 0 ? f.colour_intrinsics : f.intrinsics;
  if (f.has_colour() && ci.width > 0 && ci.height > 0 &&
      f.colour.size() == std::size_t(ci.width) * std::size_t(ci.height) * 3) {
    cv::Mat rgb(ci.height, ci.width, CV_8UC3, const_cast<std::uint8_t*>(f.colour.data()));
    cv::Mat bgr;
    cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
    panels.push_back(bgr);
  }
  if (panels.empty()) throw DeviceError("the scanner's frame has neither a depth nor a colour image to preview");
  const int h = std::min(panels[0].rows, 360);
  for (cv::Mat& p : panels)
    if (p.rows != h) cv::resize(p, p, cv::Size(std::max(1, p.cols * h / p.rows), h), 0, 0, cv::INTER_AREA);
  cv::Mat out;
  cv::hconcat(panels, out);
  std::vector<uchar> png;
  cv::imencode(".png", out, png);
  return std::string(png.begin(), png.end());
}

/// The mesh as OBJ text (vertex colours as "v x y z r g b").
std::string mesh_obj(const fs::path& ply) {
  const Mesh mesh = read_mesh(ply);
  const fs::path tmp = fs::temp_directory_path() /
                       ("station-serve-" + std::to_string(::getpid()) + "-" +
                        std::to_string(std::chrono::steady_clock::now().time_since_epoch().count()) + ".obj");
  write_obj(tmp, mesh);
  std::string bytes;
  try {
    bytes = read_file_bytes(tmp);
  } catch (...) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw;
  }
  std::error_code ec;
  fs::remove(tmp, ec);
  return bytes;
}

}  // namespace

struct StationServer::Impl {
  ServeOptions opt;
  std::string token;
  httplib::Server srv;
  std::unique_ptr<JobManager> jobs;
  int port = 0;
  std::atomic<bool> stopping{false};

  // The live preview's device, kept open between frames (opening a scanner can be slow).
  std::mutex preview_mutex;
  std::unique_ptr<DeviceRegistry> preview_registry;
  std::unique_ptr<Scanner> preview_scanner;
  std::string preview_uri;

  void close_preview_locked() {
    if (preview_scanner) {
      try {
        preview_scanner->close();
      } catch (const Error&) {
      }
    }
    preview_scanner.reset();
    preview_registry.reset();
    preview_uri.clear();
  }

  std::string session_name(const httplib::Request& req) const {
    const std::string name = req.matches[1];
    jobs->session_dir(name);  // InvalidInput for a bad name
    return name;
  }
  fs::path existing_session(const std::string& name) const {
    const fs::path dir = jobs->session_dir(name);
    std::error_code ec;
    if (!fs::is_regular_file(dir / kManifestName, ec)) throw NotFound("session " + name + ": no such session");
    return dir;
  }

  /// A file of a session named by a client: every component a plain name, and the
  /// resolved path (symbolic links followed) inside the session folder.
  fs::path session_file(const std::string& name, const std::string& rel) const {
    const fs::path dir = existing_session(name);
    fs::path p = dir;
    std::size_t pos = 0;
    while (pos <= rel.size()) {
      std::size_t end = rel.find('/', pos);
      if (end == std::string::npos) end = rel.size();
      const std::string part = rel.substr(pos, end - pos);
      if (!safe_component(part)) throw HttpError(400, "file \"" + rel + "\": not a file name inside the session");
      p /= part;
      pos = end + 1;
    }
    std::error_code ec;
    const fs::path real = fs::canonical(p, ec);
    if (ec || !fs::is_regular_file(real, ec)) throw NotFound("session " + name + ": no file " + rel);
    const std::string root = fs::canonical(dir).string() + "/";
    if (real.string().compare(0, root.size(), root) != 0)
      throw HttpError(403, "file \"" + rel + "\": outside the session");
    return real;
  }

  Json session_summary(const fs::path& dir) const {
    const std::string name = dir.filename().string();
    Json j = {{"name", name}};
    std::error_code ec;
    try {
      const SessionManifest m = manifest_from_yaml(read_file_bytes(dir / kManifestName), (dir / kManifestName).string());
      j["views"] = m.views.size();
      j["planned_views"] = m.planned_views;
      j["created"] = m.created;
      j["scanner"] = m.scanner;
    } catch (const Error& e) {
      j["error"] = e.what();
    }
    j["run"] = fs::exists(dir / "run" / "run.yaml", ec);
    j["mesh"] = fs::exists(dir / "run" / "mesh.ply", ec);
    const std::string job = jobs->job_on_session(name);
    j["job"] = job.empty() ? Json(nullptr) : Json(job);
    return j;
  }

  Json session_detail(const std::string& name) const {
    std::error_code ec;
    if (const std::string job = jobs->job_on_session(name);
        !job.empty() && !fs::is_regular_file(jobs->session_dir(name) / kManifestName, ec))
      // A scan that has just started: its folder comes with its first device frame.
      return {{"name", name}, {"views", 0}, {"planned_views", 0}, {"view_list", Json::array()},
              {"files", Json::object()}, {"job", job}};
    const fs::path dir = existing_session(name);
    Json j = session_summary(dir);
    const SessionManifest m = read_manifest(dir);
    j["turntable"] = m.turntable;
    j["units"] = m.units;
    j["axis"] = m.axis.has_value();
    Json views = Json::array();
    for (std::size_t i = 0; i < m.views.size(); ++i) {
      const ViewRecord& v = m.views[i];
      views.push_back({{"index", i},
                       {"file", v.file},
                       {"angle", v.angle_deg ? Json(*v.angle_deg) : Json(nullptr)},
                       {"points", v.points},
                       {"colour_image", v.colour_image}});
    }
    j["view_list"] = views;
    Json files = Json::object();
    for (const char* f : {"merged.ply", "run/merged.ply", "run/consolidated.ply", "run/mesh.ply", "run/report.html",
                          "run/run.yaml"})
      files[f] = fs::is_regular_file(dir / f, ec);
    j["files"] = files;
    if (fs::exists(dir / "run" / "run.yaml", ec)) {
      try {
        Json stages = Json::array();
        for (const StageRecord& s : read_run_stages(dir / "run" / "run.yaml")) {
          Json st = {{"name", s.name},       {"seconds", s.seconds}, {"peak_rss_mb", s.peak_rss_mb},
                     {"reused", s.reused},   {"output", s.output},   {"figures", s.figures}};
          if (!s.per_view.empty()) st["per_view"] = s.per_view;
          if (!s.view_prior.empty()) st["view_prior"] = s.view_prior;
          stages.push_back(st);
        }
        j["stages"] = stages;
      } catch (const Error& e) {
        j["run_error"] = e.what();
      }
    }
    return j;
  }

  /// The views in the object frame, evenly thinned to at most `max_points`: moved
  /// by the run's registered poses (`turntable` false; failed views left out) or
  /// by the turntable prior (true: the cloud growing during a scan). Little-endian
  /// uint32 count n, uint32 views, float32 xyz[3n], uint16 view[n], uint8 rgb[3n]
  /// (zeros without colours).
  std::string view_cloud(const std::string& name, std::size_t max_points, bool turntable) const {
    const fs::path dir = existing_session(name);
    const Session session = Session::open(dir);
    const SessionManifest& m = session.manifest();
    std::vector<std::optional<Eigen::Matrix4d>> poses(m.views.size());
    if (turntable) {
      if (!m.axis) throw NotFound("session " + name + ": no turntable axis to place its views by");
      for (std::size_t i = 0; i < m.views.size(); ++i)
        if (m.views[i].angle_deg) poses[i] = turntable_pose(*m.axis, *m.views[i].angle_deg);
    } else {
      std::error_code ec;
      if (!fs::exists(dir / "run" / "run.yaml", ec)) throw NotFound("session " + name + ": not registered yet (no run)");
      const StageRecord* reg = nullptr;
      const std::vector<StageRecord> stages = read_run_stages(dir / "run" / "run.yaml");
      for (const StageRecord& s : stages)
        if (s.name == "register") reg = &s;
      if (!reg || reg->poses.size() != m.views.size()) throw NotFound("session " + name + ": its run has no registered poses");
      for (std::size_t i = 0; i < m.views.size(); ++i) {
        if (i < reg->view_prior.size() && reg->view_prior[i] == "failed") continue;
        Eigen::Matrix4d T;
        for (int k = 0; k < 16; ++k) T(k / 4, k % 4) = reg->poses[i][k];
        poses[i] = T;
      }
    }
    std::size_t total = 0;
    for (const ViewRecord& v : m.views) total += v.points;
    const std::size_t stride = std::max<std::size_t>(1, (total + max_points - 1) / max_points);
    std::vector<float> xyz;
    std::vector<std::uint16_t> view;
    std::vector<std::uint8_t> rgb;
    for (std::size_t i = 0; i < m.views.size(); ++i) {
      if (!poses[i]) continue;
      const Cloud c = session.load_view(i);
      const Eigen::Matrix4d& T = *poses[i];
      for (std::size_t k = 0; k < c.size(); k += stride) {
        const Eigen::Vector3d p = (T * c.points[k].cast<double>().homogeneous()).head<3>();
        xyz.insert(xyz.end(), {float(p.x()), float(p.y()), float(p.z())});
        view.push_back(std::uint16_t(i));
        if (c.has_colours()) rgb.insert(rgb.end(), {c.colours[k].r, c.colours[k].g, c.colours[k].b});
        else rgb.insert(rgb.end(), {std::uint8_t(0), std::uint8_t(0), std::uint8_t(0)});
      }
    }
    std::string out(8 + xyz.size() * 4 + view.size() * 2 + rgb.size(), '\0');
    const std::uint32_t n = std::uint32_t(view.size()), nv = std::uint32_t(m.views.size());
    std::memcpy(&out[0], &n, 4);
    std::memcpy(&out[4], &nv, 4);
    std::size_t at = 8;
    if (!xyz.empty()) std::memcpy(&out[at], xyz.data(), xyz.size() * 4);
    at += xyz.size() * 4;
    if (!view.empty()) std::memcpy(&out[at], view.data(), view.size() * 2);
    at += view.size() * 2;
    if (!rgb.empty()) std::memcpy(&out[at], rgb.data(), rgb.size());
    return out;
  }

  std::string preview(const std::string& profile, const std::string& scanner) {
    const std::string uri = jobs->devices_for(profile, scanner, {}).first;
    std::lock_guard<std::mutex> lock(preview_mutex);
    if (const std::string id = jobs->job_on_device(uri); !id.empty())
      throw JobBusy(device_key(uri) + ": in use by job " + id + "; the preview comes back when it ends");
    if (preview_uri != uri || !preview_scanner) {
      close_preview_locked();
      preview_registry = std::make_unique<DeviceRegistry>(cli::make_registry());
      auto s = preview_registry->make_scanner(uri);
      s->open();
      preview_scanner = std::move(s);
      preview_uri = uri;
    }
    try {
      return preview_png(preview_scanner->grab());
    } catch (const Error&) {
      close_preview_locked();  // an unplugged device is reopened on the next frame
      throw;
    }
  }

  /// Refuses what the server must not answer: a Host other than loopback while
  /// bound to it without a token (a page elsewhere reaching us by DNS rebinding),
  /// a missing or wrong token, a POST that is not JSON or comes from another origin.
  httplib::Server::HandlerResponse guard(const httplib::Request& req, httplib::Response& res) const {
    if (req.path.rfind("/api/", 0) != 0) return httplib::Server::HandlerResponse::Unhandled;
    const std::string host = req.get_header_value("Host");
    if (token.empty() && !is_loopback_address(host_name(host))) {
      send_error(res, 403, "Host \"" + host + "\": this station serves loopback only (start it with a token to serve others)");
      return httplib::Server::HandlerResponse::Handled;
    }
    if (!token.empty()) {
      std::string given = req.get_header_value("X-Station-Token");
      const std::string auth = req.get_header_value("Authorization");
      if (given.empty() && auth.rfind("Bearer ", 0) == 0) given = auth.substr(7);
      if (given.empty()) given = cookie(req, "station_token");
      if (given.empty()) {
        send_error(res, 401, "this station needs its token (Authorization: Bearer, X-Station-Token or the station_token cookie)");
        return httplib::Server::HandlerResponse::Handled;
      }
      if (!same_secret(given, token)) {
        send_error(res, 403, "wrong token");
        return httplib::Server::HandlerResponse::Handled;
      }
    }
    if (req.method == "POST") {
      const std::string type = req.get_header_value("Content-Type");
      if (type.rfind("application/json", 0) != 0) {
        send_error(res, 415, "POST " + req.path + ": the body must be JSON (Content-Type: application/json)");
        return httplib::Server::HandlerResponse::Handled;
      }
      const std::string origin = req.get_header_value("Origin");
      if (!origin.empty() && origin != "http://" + host) {
        send_error(res, 403, "Origin \"" + origin + "\": requests from other sites are refused");
        return httplib::Server::HandlerResponse::Handled;
      }
    }
    return httplib::Server::HandlerResponse::Unhandled;
  }

  void routes();
};

void StationServer::Impl::routes() {
  srv.Get("/api/status", api([this](const httplib::Request&, httplib::Response& res) {
    send_json(res, 200,
              {{"version", STATION_VERSION}, {"data", jobs->data_dir().string()}, {"token", !token.empty()},
               {"jobs", jobs->list().size()}});
  }));
  srv.Get("/api/devices", api([this](const httplib::Request&, httplib::Response& res) {
    Json list = Json::array();
    for (const DeviceInfo& d : cli::make_registry().list()) {
      const std::string job = jobs->job_on_device(d.uri);
      list.push_back({{"uri", d.uri},
                      {"kind", d.kind == DeviceKind::kScanner ? "scanner" : "turntable"},
                      {"description", d.description},
                      {"available", d.available},
                      {"job", job.empty() ? Json(nullptr) : Json(job)}});
    }
    send_json(res, 200, {{"devices", list}});
  }));
  srv.Get("/api/profiles", api([this](const httplib::Request&, httplib::Response& res) {
    std::vector<fs::path> files;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(jobs->profile_dir(), ec))
      if (e.path().extension() == ".yaml" && safe_component(e.path().filename().string())) files.push_back(e.path());
    std::sort(files.begin(), files.end());
    Json list = Json::array();
    for (const fs::path& f : files) {
      Json p = {{"name", f.filename().string()}};
      try {
        const StationConfig cfg = load_config(f);
        p["scanner"] = compose_uri(cfg.scanner_uri, cfg.scanner_options);
        p["turntable"] = compose_uri(cfg.turntable_uri, cfg.turntable_options);
        p["views"] = cfg.capture.views;
      } catch (const Error& e) {
        p["error"] = e.what();
      }
      list.push_back(p);
    }
    send_json(res, 200, {{"profiles", list}});
  }));
  srv.Get("/api/sessions", api([this](const httplib::Request&, httplib::Response& res) {
    std::vector<std::pair<fs::file_time_type, fs::path>> dirs;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(jobs->data_dir(), ec)) {
      const std::string n = e.path().filename().string();
      if (!safe_component(n) || !fs::is_regular_file(e.path() / kManifestName, ec)) continue;
      dirs.push_back({fs::last_write_time(e.path() / kManifestName, ec), e.path()});
    }
    std::sort(dirs.begin(), dirs.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
    Json list = Json::array();
    for (const auto& [t, d] : dirs) list.push_back(session_summary(d));
    send_json(res, 200, {{"sessions", list}});
  }));
  srv.Get(R"(/api/sessions/([^/]+))", api([this](const httplib::Request& req, httplib::Response& res) {
    send_json(res, 200, session_detail(session_name(req)));
  }));
  srv.Get(R"(/api/sessions/([^/]+)/files/(.+))", api([this](const httplib::Request& req, httplib::Response& res) {
    const fs::path f = session_file(session_name(req), req.matches[2]);
    res.set_header("Cache-Control", "no-store");
    if (req.has_param("download"))
      res.set_header("Content-Disposition", "attachment; filename=\"" + session_name(req) + "-" + f.filename().string() + "\"");
    res.set_content(read_file_bytes(f), content_type(f));
  }));
  srv.Get(R"(/api/sessions/([^/]+)/mesh\.obj)", api([this](const httplib::Request& req, httplib::Response& res) {
    const std::string name = session_name(req);
    const fs::path ply = session_file(name, "run/mesh.ply");
    res.set_header("Content-Disposition", "attachment; filename=\"" + name + "-mesh.obj\"");
    res.set_content(mesh_obj(ply), "text/plain; charset=utf-8");
  }));
  srv.Get(R"(/api/sessions/([^/]+)/cloud)", api([this](const httplib::Request& req, httplib::Response& res) {
    std::size_t max_points = 60000;
    if (req.has_param("max")) {
      const std::string m = req.get_param_value("max");
      if (m.empty() || m.size() > 7 || !std::all_of(m.begin(), m.end(), ::isdigit) || std::stoul(m) == 0)
        throw HttpError(400, "max \"" + m + "\": expected 1-9999999 points");
      max_points = std::stoul(m);
    }
    res.set_header("Cache-Control", "no-store");
    const bool turntable = req.has_param("poses") && req.get_param_value("poses") == "turntable";
    res.set_content(view_cloud(session_name(req), max_points, turntable), "application/octet-stream");
  }));
  srv.Post("/api/scan", api([this](const httplib::Request& req, httplib::Response& res) {
    const Json b = json_body(req);
    ScanJobRequest r;
    r.session = get_string(b, "session");
    r.profile = get_string(b, "profile");
    r.scanner = get_string(b, "scanner");
    r.turntable = get_string(b, "turntable");
    r.views = get_int(b, "views");
    r.resume = get_bool(b, "resume", false);
    r.run = get_bool(b, "run", true);
    if (r.session.empty()) {
      // scan-YYYYMMDD-HHMMSS, with a suffix when that exists already.
      const std::time_t now = std::time(nullptr);
      std::tm tm{};
      ::gmtime_r(&now, &tm);
      char buf[32];
      std::strftime(buf, sizeof buf, "scan-%Y%m%d-%H%M%S", &tm);
      r.session = buf;
      std::error_code ec;
      for (int k = 2; fs::exists(jobs->data_dir() / r.session, ec); ++k) r.session = std::string(buf) + "-" + std::to_string(k);
    }
    const std::string id = jobs->start_scan(r);
    send_json(res, 202, {{"job", id}, {"session", r.session}});
  }));
  srv.Post("/api/run", api([this](const httplib::Request& req, httplib::Response& res) {
    const Json b = json_body(req);
    RunJobRequest r;
    r.session = get_string(b, "session");
    r.profile = get_string(b, "profile");
    r.resume = get_bool(b, "resume", false);
    const std::string id = jobs->start_run(r);
    send_json(res, 202, {{"job", id}, {"session", r.session}});
  }));
  srv.Post(R"(/api/jobs/(\d+)/stop)", api([this](const httplib::Request& req, httplib::Response& res) {
    jobs->stop(req.matches[1]);
    send_json(res, 200, job_json(jobs->info(req.matches[1])));
  }));
  srv.Get("/api/jobs", api([this](const httplib::Request&, httplib::Response& res) {
    Json list = Json::array();
    for (const JobInfo& i : jobs->list()) list.push_back(job_json(i));
    send_json(res, 200, {{"jobs", list}});
  }));
  srv.Get(R"(/api/jobs/(\d+))", api([this](const httplib::Request& req, httplib::Response& res) {
    send_json(res, 200, job_json(jobs->info(req.matches[1])));
  }));
  srv.Get(R"(/api/jobs/(\d+)/events)", api([this](const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    jobs->info(id);  // 404 before the stream starts
    std::size_t from = 0;
    std::string start = req.has_param("from") ? req.get_param_value("from") : req.get_header_value("Last-Event-ID");
    if (!start.empty()) {
      if (start.size() > 9 || !std::all_of(start.begin(), start.end(), ::isdigit))
        throw HttpError(400, "from \"" + start + "\": expected an event number");
      from = std::stoul(start) + (req.has_param("from") ? 0 : 1);  // Last-Event-ID is the last one seen
    }
    auto next = std::make_shared<std::size_t>(from);
    auto last_write = std::make_shared<std::chrono::steady_clock::time_point>(std::chrono::steady_clock::now());
    res.set_header("Cache-Control", "no-store");
    res.set_header("X-Accel-Buffering", "no");
    res.set_chunked_content_provider(
        "text/event-stream", [this, id, next, last_write](std::size_t, httplib::DataSink& sink) {
          if (stopping) {
            sink.done();
            return true;
          }
          bool ended = false;
          const std::vector<std::string> ev = jobs->events(id, *next, std::chrono::milliseconds(500), &ended);
          std::string out;
          for (const std::string& e : ev) out += "id: " + std::to_string((*next)++) + "\ndata: " + e + "\n\n";
          const auto now = std::chrono::steady_clock::now();
          if (out.empty() && now - *last_write > std::chrono::seconds(15)) out = ": still working\n\n";
          if (!out.empty()) {
            // A client that went away ends the stream, never the job.
            if (!sink.is_writable() || !sink.write(out.data(), out.size())) return false;
            *last_write = now;
          }
          if (ended && ev.empty()) sink.done();
          return true;
        });
  }));
  srv.Get("/api/preview.png", api([this](const httplib::Request& req, httplib::Response& res) {
    const std::string png =
        preview(req.has_param("profile") ? req.get_param_value("profile") : "",
                req.has_param("scanner") ? req.get_param_value("scanner") : "");
    res.set_header("Cache-Control", "no-store");
    res.set_content(png, "image/png");
  }));
  // Anything else under /api is an unknown request, as JSON.
  srv.set_error_handler([](const httplib::Request& req, httplib::Response& res) {
    if (req.path.rfind("/api/", 0) == 0 && res.body.empty())
      send_error(res, res.status,
                 req.method + " " + req.path + (res.status == 404 ? ": no such request (docs/serve.md lists them)"
                                                                  : ": refused (HTTP " + std::to_string(res.status) + ")"));
  });
}

StationServer::StationServer(const ServeOptions& options) : impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  m.opt = options;
  if (!options.token_file.empty()) m.token = read_token_file(options.token_file);
  if (m.token.empty() && !is_loopback_address(options.bind))
    throw InvalidInput("--bind " + options.bind +
                       ": serving beyond loopback needs a token (--token-file FILE, 16 or more characters)");
  if (options.port < 0 || options.port > 65535)
    throw InvalidInput("--port " + std::to_string(options.port) + ": expected 0-65535");
  const fs::path web = options.web_dir.empty() ? fs::path(STATION_SOURCE_DIR) / "web" : options.web_dir;
  const fs::path three = options.three_dir.empty() ? fs::path(STATION_THREE_DIR) : options.three_dir;
  fs::path profiles = options.profile_dir;
  if (profiles.empty()) {
    const fs::path def = default_config_path();
    profiles = def.empty() ? fs::path(STATION_SOURCE_DIR) / "config" : def.parent_path();
  }
  std::error_code ec;
  if (!fs::is_regular_file(web / "index.html", ec))
    throw InvalidInput(web.string() + ": no index.html (the station page) there");
  if (!fs::is_regular_file(three / "build" / "three.module.js", ec))
    throw InvalidInput(three.string() + ": no three.js (Debian's libjs-three: scripts/setup.sh installs it)");
  m.jobs = std::make_unique<JobManager>(options.data_dir, profiles, options.threads);
  m.jobs->set_device_release([this](const std::string& key) {
    std::lock_guard<std::mutex> lock(impl_->preview_mutex);
    if (!impl_->preview_uri.empty() && device_key(impl_->preview_uri) == key) impl_->close_preview_locked();
  });
  m.srv.set_mount_point("/vendor/three", three.string());
  m.srv.set_mount_point("/", web.string());
  m.srv.set_file_extension_and_mimetype_mapping("js", "text/javascript");
  m.srv.set_default_headers({{"X-Content-Type-Options", "nosniff"},
                             {"X-Frame-Options", "DENY"},
                             {"Referrer-Policy", "no-referrer"},
                             {"Content-Security-Policy",
                              "default-src 'self'; img-src 'self' blob: data:; style-src 'self' 'unsafe-inline'"}});
  m.srv.set_payload_max_length(1 << 20);
  m.srv.new_task_queue = [] { return new httplib::ThreadPool(16); };
  m.srv.set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
    return impl_->guard(req, res);
  });
  m.srv.set_exception_handler([](const httplib::Request&, httplib::Response& res, std::exception_ptr) {
    send_error(res, 500, "internal error");
  });
  m.routes();
  if (options.port == 0) {
    m.port = m.srv.bind_to_any_port(options.bind);
    if (m.port <= 0) throw IoError(options.bind + ": cannot listen on any port");
  } else {
    if (!m.srv.bind_to_port(options.bind, options.port))
      throw IoError(options.bind + ":" + std::to_string(options.port) +
                    ": cannot listen there (in use, or not an address of this machine)");
    m.port = options.port;
  }
}

StationServer::~StationServer() {
  stop();
  impl_->jobs.reset();  // asks every job to stop and waits for them
  std::lock_guard<std::mutex> lock(impl_->preview_mutex);
  impl_->close_preview_locked();
}

int StationServer::port() const { return impl_->port; }

void StationServer::listen() { impl_->srv.listen_after_bind(); }

void StationServer::stop() {
  impl_->stopping = true;
  impl_->srv.stop();
}

JobManager& StationServer::jobs() { return *impl_->jobs; }

}  // namespace station
