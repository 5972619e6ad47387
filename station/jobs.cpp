#include "station/jobs.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <new>
#include <optional>
#include <tuple>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/threads.h"
#include "drivers/registry.h"
#include "station/commands.h"
#include "station/config.h"
#include "station/pipeline.h"
#include "station/progress.h"

namespace station {

namespace fs = std::filesystem;
using Json = nlohmann::json;

const char* to_string(JobState s) {
  switch (s) {
    case JobState::kRunning: return "running";
    case JobState::kFinished: return "finished";
    case JobState::kFailed: return "failed";
    case JobState::kStopped: return "stopped";
  }
  return "?";
}

bool safe_component(const std::string& name) {
  if (name.empty() || name.size() > 128 || name == "." || name == ".." || name[0] == '.') return false;
  return name.find('/') == std::string::npos && name.find('\\') == std::string::npos &&
         name.find('\0') == std::string::npos;
}

std::string device_key(const std::string& uri) {
  const DeviceUri u = parse_device_uri(uri);
  return u.scheme + ":" + u.path;
}

namespace {

/// `e` again, of the same type, with `message`.
[[noreturn]] void rethrow_as(const Error& e, const std::string& message) {
  if (dynamic_cast<const DeviceError*>(&e)) throw DeviceError(message);
  if (dynamic_cast<const IoError*>(&e)) throw IoError(message);
  if (dynamic_cast<const FormatError*>(&e)) throw FormatError(message);
  throw InvalidInput(message);
}

constexpr std::size_t kMaxEvents = 200000;  ///< steps beyond this are dropped (lines, views, stages never)

}  // namespace

struct JobManager::Job {
  JobInfo info;                  ///< guarded by m
  std::vector<std::string> devices;  ///< device keys held (guarded by the manager's mutex)
  std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();
  std::atomic<bool> stop{false};
  bool interrupted = false;      ///< the work returned early on `stop`
  mutable std::mutex m;
  mutable std::condition_variable cv;
  std::vector<std::string> events;  ///< guarded by m
  std::thread thread;

  double elapsed() const { return seconds_since(t0); }
  void emit(Json j) {
    std::lock_guard<std::mutex> lock(m);
    emit_locked(std::move(j));
  }
  void emit_locked(Json j) {
    if (events.size() >= kMaxEvents && j.value("type", "") == "step") return;
    j["seq"] = events.size();
    j["t"] = std::round(elapsed() * 1000) / 1000;
    events.push_back(j.dump());
    info.events = events.size();
    cv.notify_all();
  }
  /// The pipeline's and the capture's progress, as events.
  ProgressSink sink() {
    return [this](const ProgressEvent& e) {
      switch (e.kind) {
        case ProgressEvent::Kind::kLine: emit({{"type", "line"}, {"text", e.text}}); break;
        case ProgressEvent::Kind::kStep:
          emit({{"type", "step"}, {"label", e.label}, {"done", e.done}, {"total", e.total}, {"note", e.text},
                {"seconds", e.seconds}});
          break;
        case ProgressEvent::Kind::kFinish:
          emit({{"type", "finish"}, {"label", e.label}, {"note", e.text}, {"seconds", e.seconds}});
          break;
        case ProgressEvent::Kind::kStage:
          emit({{"type", "stage"}, {"stage", e.label}, {"status", e.text}, {"index", e.done}, {"total", e.total},
                {"seconds", e.seconds}});
          break;
      }
    };
  }
};

JobManager::JobManager(fs::path data_dir, fs::path profile_dir, int threads)
    : data_dir_(std::move(data_dir)), profile_dir_(std::move(profile_dir)), threads_(threads) {
  // The reason is create_directories' (read-only file system, permission denied),
  // not is_directory's "no such file" that follows from it.
  std::error_code made, ec;
  fs::create_directories(data_dir_, made);
  if (!fs::is_directory(data_dir_, ec)) {
    const std::error_code& why = made ? made : ec;
    throw IoError(data_dir_.string() + ": cannot create the data folder" + (why ? ": " + why.message() : ""));
  }
  data_dir_ = fs::canonical(data_dir_);
}

JobManager::~JobManager() {
  std::vector<std::shared_ptr<Job>> all;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto& [id, job] : jobs_) all.push_back(job);
  }
  for (auto& job : all) job->stop = true;
  for (auto& job : all)
    if (job->thread.joinable()) job->thread.join();
}

fs::path JobManager::session_dir(const std::string& name) const {
  const bool ok = safe_component(name) && name.size() <= 64 &&
                  std::all_of(name.begin(), name.end(), [](char ch) {
                    return std::isalnum(static_cast<unsigned char>(ch)) || ch == '.' || ch == '_' || ch == '-';
                  });
  if (!ok)
    throw InvalidInput("session \"" + name +
                       "\": a session name is 1-64 letters, digits, '.', '_' or '-', not starting with '.'");
  return data_dir_ / name;
}

fs::path JobManager::profile_path(const std::string& name) const {
  std::string n = name.empty() ? "default.yaml" : name;
  std::error_code ec;
  if (name.empty() && !fs::is_regular_file(profile_dir_ / n, ec)) {
    // No default.yaml there: the first profile by name.
    std::vector<std::string> all;
    for (const auto& e : fs::directory_iterator(profile_dir_, ec))
      if (e.path().extension() == ".yaml" && safe_component(e.path().filename().string()))
        all.push_back(e.path().filename().string());
    std::sort(all.begin(), all.end());
    if (!all.empty()) n = all.front();
  }
  const fs::path p = profile_dir_ / n;
  if (!safe_component(n) || fs::path(n).extension() != ".yaml" || !fs::is_regular_file(p, ec))
    throw InvalidInput("profile \"" + n + "\": not a profile of " + profile_dir_.string() + " (GET /api/profiles lists them)");
  return p;
}

std::shared_ptr<JobManager::Job> JobManager::find(const std::string& id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) throw NotFound("job " + id + ": no such job");
  return it->second;
}

std::shared_ptr<JobManager::Job> JobManager::add(const std::string& kind, const std::string& session,
                                                 const std::string& device) {
  // Called with mutex_ held.
  auto job = std::make_shared<Job>();
  job->info.id = std::to_string(next_id_++);
  job->info.kind = kind;
  job->info.session = session;
  job->info.device = device;
  jobs_[job->info.id] = job;
  return job;
}

void JobManager::launch(const std::shared_ptr<Job>& job, std::function<void(Job&)> work) {
  job->thread = std::thread([this, job, work = std::move(work)] {
    std::string error;
    try {
      work(*job);
    } catch (const Error& e) {
      error = e.what();
    } catch (const std::bad_alloc&) {
      error = "out of memory";
    } catch (const std::exception& e) {
      error = std::string("internal error: ") + e.what();
    }
    {
      std::lock_guard<std::mutex> lock(mutex_);
      job->devices.clear();
    }
    JobState state = !error.empty() ? JobState::kFailed : job->interrupted ? JobState::kStopped : JobState::kFinished;
    Json end = {{"type", "end"}, {"state", to_string(state)}};
    if (!error.empty()) end["error"] = error;
    // The state and the last event change together: a reader that sees the job
    // ended has its end event too.
    std::lock_guard<std::mutex> lock(job->m);
    job->info.state = state;
    job->info.error = error;
    job->info.device.clear();
    job->info.seconds = job->elapsed();
    job->emit_locked(end);
  });
}

namespace {

/// The run of a session into <session>/run, reporting to the job.
bool run_session(const StationConfig& cfg, const fs::path& dir, bool resume, const ProgressSink& sink,
                 const std::atomic<bool>* stop) {
  RunRequest req;
  req.input = dir;
  req.out_dir = dir / "run";
  std::error_code ec;
  req.resume = resume || fs::exists(req.out_dir / "run.yaml", ec);
  req.quiet = true;
  req.stop = stop;
  req.events = sink;
  RunResult r;
  try {
    r = run_pipeline(cfg, req);
  } catch (const IoError& e) {
    if (!fs::exists(req.out_dir / "run.yaml", ec)) throw;
    throw IoError(std::string(e.what()) + "; finished stages in " + req.out_dir.string() +
                  " are intact: fix the cause (a full disk: free space) and run it again");
  }
  return !r.interrupted;
}

}  // namespace

std::pair<std::string, std::string> JobManager::devices_for(const std::string& profile, const std::string& scanner,
                                                            const std::string& turntable) const {
  const StationConfig cfg = load_config(profile_path(profile));
  // A client picks among the devices the station offers (the profile's, the listed
  // ones): never a URI of its own, whose options could name files outside the data folder.
  const std::string own_scanner = compose_uri(cfg.scanner_uri, cfg.scanner_options);
  const std::string own_turntable = compose_uri(cfg.turntable_uri, cfg.turntable_options);
  std::vector<DeviceInfo> listed;
  const auto offered = [&](const std::string& uri, const std::string& own, DeviceKind kind) {
    if (uri.empty() || uri == own) return true;
    if (listed.empty()) listed = cli::make_registry().list();
    for (const DeviceInfo& d : listed)
      if (d.kind == kind && d.uri == uri) return true;
    return false;
  };
  if (!offered(scanner, own_scanner, DeviceKind::kScanner))
    throw InvalidInput("scanner \"" + scanner + "\": not the profile's nor one of GET /api/devices' scanners");
  if (!offered(turntable, own_turntable, DeviceKind::kTurntable))
    throw InvalidInput("turntable \"" + turntable + "\": not the profile's nor one of GET /api/devices' turntables");
  return {scanner.empty() ? own_scanner : scanner, turntable.empty() ? own_turntable : turntable};
}

std::string JobManager::start_scan(const ScanJobRequest& r) {
  const fs::path dir = session_dir(r.session);
  if (const std::string id = job_on_session(r.session); !id.empty())
    throw JobBusy("session " + r.session + ": job " + id + " is working on it; stop it or wait until it ends");
  std::error_code ec;
  if (r.resume && !fs::exists(dir / kManifestName, ec))
    throw NotFound("session " + r.session + ": no such session to resume");
  const fs::path profile = profile_path(r.profile);
  if (r.views < 0 || r.views > 3600)
    throw InvalidInput("views: " + std::to_string(r.views) + " (expected 1-3600, or 0 for the profile's)");
  std::vector<std::string> overrides;
  if (r.views > 0) overrides.push_back("capture.views=" + std::to_string(r.views));
  StationConfig cfg = load_config(profile, overrides);
  cfg.threads = threads_;
  std::string scanner_uri, turntable_uri;
  std::tie(scanner_uri, turntable_uri) = devices_for(r.profile, r.scanner, r.turntable);
  if (r.resume) {
    const SessionManifest m = read_manifest(dir);
    // Resume with the devices and the plan the session was started with.
    if (!m.scanner.empty()) scanner_uri = m.scanner;
    if (!m.turntable.empty()) turntable_uri = m.turntable;
    if (m.planned_views > 0) {
      cfg.capture.views = m.planned_views;
      cfg.capture.start_deg = m.start_deg;
      cfg.capture.step_deg = m.step_deg;
    }
  } else if (fs::exists(dir, ec)) {
    throw InvalidInput("session " + r.session + ": exists already; resume it or choose another name");
  }
  const std::string scanner_key = device_key(scanner_uri);
  const std::string turntable_key = device_key(turntable_uri);

  std::shared_ptr<Job> job;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [id, other] : jobs_) {
      for (const std::string& k : other->devices)
        if (k == scanner_key || k == turntable_key)
          throw JobBusy(k + ": in use by job " + id + " (scan of " + other->info.session +
                        "); stop it or wait until it ends");
      std::lock_guard<std::mutex> jl(other->m);
      if (other->info.state == JobState::kRunning && other->info.session == r.session)
        throw JobBusy("session " + r.session + ": job " + id + " is working on it; stop it or wait until it ends");
    }
    job = add("scan", r.session, scanner_uri);
    job->devices = {scanner_key, turntable_key};
  }
  if (release_) {
    release_(scanner_key);
    release_(turntable_key);
  }
  const bool resume = r.resume, then_run = r.run;
  launch(job, [this, cfg, dir, scanner_uri, turntable_uri, resume, then_run](Job& j) {
    DeviceRegistry reg = cli::make_registry();
    auto scanner = reg.make_scanner(scanner_uri);
    auto turntable = reg.make_turntable(turntable_uri);
    scanner->open();
    turntable->open();
    std::optional<Session> session;
    if (resume) {
      session = Session::open(dir);
    } else {
      SessionManifest m;
      m.scanner = scanner_uri;
      m.turntable = turntable_uri;
      session = Session::create(dir, m);
    }
    j.emit({{"type", "line"}, {"text", "scan: " + std::to_string(cfg.capture.views) + " views with " + scanner_uri}});
    Progress bar("scan", cfg.capture.views, true, j.sink());
    CaptureResult res;
    try {
      res = run_capture(
          *scanner, *turntable, *session, cfg.capture,
          [&](const CaptureProgress& p) {
            const auto& views = session->manifest().views;
            const std::string image = p.view < int(views.size()) ? views[p.view].colour_image : "";
            j.emit({{"type", "view"}, {"view", p.view}, {"total", p.total}, {"angle", p.angle_deg},
                    {"points", p.points}, {"colour_image", image}, {"file", p.view < int(views.size()) ? views[p.view].file : ""}});
            bar.update(p.view + 1);
          },
          &j.stop);
    } catch (const Error& e) {
      const std::size_t kept = session->manifest().views.size();
      // A new session whose first view failed leaves nothing (its name was free: the
      // stub blocked the next try as "exists already").
      if (!resume) cli::drop_unrecorded_session(*session, false);
      rethrow_as(e, std::string(e.what()) +
                        (kept == 0 ? "; nothing was recorded"
                                   : "; the " + std::to_string(kept) +
                                         " views recorded before it are kept: once the cause is fixed, resume the scan"));
    }
    scanner->close();
    turntable->close();
    {
      std::lock_guard<std::mutex> lock(mutex_);
      j.devices.clear();
    }
    {
      std::lock_guard<std::mutex> lock(j.m);
      j.info.device.clear();
    }
    if (res.interrupted) {
      j.interrupted = true;
      j.emit({{"type", "line"},
              {"text", "scan: stopped after " + std::to_string(session->manifest().views.size()) +
                           " views; resume it to go on"}});
      return;
    }
    bar.finish();
    try {
      if (const std::string w = cli::check_recorded_points(*session, std::size_t(res.resumed_from)); !w.empty())
        j.emit({{"type", "line"}, {"text", "warning: " + w}});
    } catch (const cli::NoPointsRecorded& e) {
      if (resume) throw;
      cli::drop_unrecorded_session(*session, false, true);
      throw cli::NoPointsRecorded(std::string(e.what()) + "; nothing was kept");
    }
    cli::write_merged(*session, dir / "merged.ply", true);
    if (!then_run) return;
    if (!run_session(cfg, dir, false, j.sink(), &j.stop)) j.interrupted = true;
  });
  return job->info.id;
}

std::string JobManager::start_run(const RunJobRequest& r) {
  const fs::path dir = session_dir(r.session);
  // A session being scanned is busy even before its folder exists.
  if (const std::string id = job_on_session(r.session); !id.empty())
    throw JobBusy("session " + r.session + ": job " + id + " is working on it; stop it or wait until it ends");
  std::error_code ec;
  if (!fs::exists(dir / kManifestName, ec)) throw NotFound("session " + r.session + ": no such session");
  StationConfig cfg = load_config(profile_path(r.profile));
  cfg.threads = threads_;
  if (fs::exists(dir / "run" / "run.yaml", ec) && !r.resume)
    throw InvalidInput("session " + r.session + ": has a run already; resume it (finished stages are kept)");
  std::shared_ptr<Job> job;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [id, other] : jobs_) {
      std::lock_guard<std::mutex> jl(other->m);
      if (other->info.state == JobState::kRunning && other->info.session == r.session)
        throw JobBusy("session " + r.session + ": job " + id + " is working on it; stop it or wait until it ends");
    }
    job = add("run", r.session, "");
  }
  const bool resume = r.resume;
  launch(job, [cfg, dir, resume](Job& j) {
    if (!run_session(cfg, dir, resume, j.sink(), &j.stop)) j.interrupted = true;
  });
  return job->info.id;
}

void JobManager::stop(const std::string& id) {
  auto job = find(id);
  job->stop = true;
  job->emit({{"type", "line"}, {"text", "stopping after the step in progress"}});
}

JobInfo JobManager::info(const std::string& id) const {
  auto job = find(id);
  std::lock_guard<std::mutex> lock(job->m);
  JobInfo i = job->info;
  if (i.state == JobState::kRunning) i.seconds = job->elapsed();
  return i;
}

std::vector<JobInfo> JobManager::list() const {
  std::vector<std::string> ids;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [id, job] : jobs_) ids.push_back(id);
  }
  std::sort(ids.begin(), ids.end(), [](const std::string& a, const std::string& b) {
    return a.size() != b.size() ? a.size() < b.size() : a < b;
  });
  std::vector<JobInfo> out;
  for (const std::string& id : ids) out.push_back(info(id));
  return out;
}

std::vector<std::string> JobManager::events(const std::string& id, std::size_t from, std::chrono::milliseconds wait,
                                            bool* ended) const {
  auto job = find(id);
  std::unique_lock<std::mutex> lock(job->m);
  job->cv.wait_for(lock, wait,
                   [&] { return job->events.size() > from || job->info.state != JobState::kRunning; });
  std::vector<std::string> out;
  for (std::size_t k = from; k < job->events.size(); ++k) out.push_back(job->events[k]);
  if (ended) *ended = job->info.state != JobState::kRunning;
  return out;
}

std::string JobManager::job_on_session(const std::string& session) const {
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [id, job] : jobs_) {
    std::lock_guard<std::mutex> jl(job->m);
    if (job->info.state == JobState::kRunning && job->info.session == session) return id;
  }
  return {};
}

std::string JobManager::job_on_device(const std::string& uri) const {
  const std::string key = device_key(uri);
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [id, job] : jobs_)
    for (const std::string& k : job->devices)
      if (k == key) return id;
  return {};
}

}  // namespace station
