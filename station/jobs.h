#pragma once
// The jobs of `station serve` (station/serve.h): a scan (optionally followed by a
// run) or a run of a session under the data folder, each on its own thread over
// the same library calls the CLI makes (run_capture, run_pipeline). One job per
// device and per session at a time; a job outlives the client that started it and
// stops only when asked (after the view or stage in progress, resumable as after
// Ctrl-C). Every job keeps the events it printed (JSON texts, docs/serve.md), so
// a client that connects late, or again, reads them from the start.
#include <chrono>
#include <condition_variable>
#include <functional>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/error.h"

namespace station {

/// A start that conflicts with a running job (HTTP 409).
class JobBusy : public Error {
 public:
  using Error::Error;
};
/// An unknown job, session or file (HTTP 404).
class NotFound : public Error {
 public:
  using Error::Error;
};

struct ScanJobRequest {
  std::string session;             ///< folder name under the data folder
  std::string profile;             ///< a profile's file name ("default.yaml"); empty: default.yaml
  std::string scanner, turntable;  ///< device URIs overriding the profile's; empty: the profile's
  int views = 0;                   ///< views over 360 degrees; 0: the profile's
  bool resume = false;             ///< continue an interrupted scan of `session`
  bool run = true;                 ///< then run the whole job into <session>/run
};

struct RunJobRequest {
  std::string session;
  std::string profile;
  bool resume = false;  ///< keep the finished stages of <session>/run
};

enum class JobState { kRunning, kFinished, kFailed, kStopped };
const char* to_string(JobState s);

struct JobInfo {
  std::string id;       ///< "1", "2", ... in start order
  std::string kind;     ///< "scan" or "run"
  std::string session;  ///< its name
  std::string device;   ///< the scanner URI a scan holds; empty for a run
  JobState state = JobState::kRunning;
  std::string error;    ///< the CLI's one-line message when failed
  double seconds = 0;   ///< so far, or in all once ended
  std::size_t events = 0;
};

class JobManager {
 public:
  /// `data_dir` holds the sessions (created when missing); `profile_dir` the
  /// profiles a request may name; `threads` as the profiles' (0: all cores).
  JobManager(std::filesystem::path data_dir, std::filesystem::path profile_dir, int threads = 0);
  /// Asks every job to stop, then waits for them.
  ~JobManager();
  JobManager(const JobManager&) = delete;
  JobManager& operator=(const JobManager&) = delete;

  /// InvalidInput for a bad name, profile or plan; JobBusy when the device or the
  /// session is in use; NotFound when resuming a session that does not exist.
  std::string start_scan(const ScanJobRequest& request);
  std::string start_run(const RunJobRequest& request);
  /// Asks the job to stop after the view or stage in progress (NotFound when unknown).
  void stop(const std::string& id);
  JobInfo info(const std::string& id) const;
  std::vector<JobInfo> list() const;
  /// The job's events from index `from` on; when there are none yet, waits up to
  /// `wait` for one. `ended` tells whether the job has ended (no events follow).
  std::vector<std::string> events(const std::string& id, std::size_t from, std::chrono::milliseconds wait,
                                  bool* ended) const;
  /// The scanner and turntable URIs a scan with `profile` uses: the profile's, or
  /// the client's choice when it is the profile's or one `station devices` lists
  /// (never an arbitrary URI, whose options could name files outside the data
  /// folder: InvalidInput).
  std::pair<std::string, std::string> devices_for(const std::string& profile, const std::string& scanner,
                                                  const std::string& turntable) const;
  /// Called with a scan's device keys ("scheme:path") after it is registered and
  /// before its thread opens them (the server closes its preview of them).
  void set_device_release(std::function<void(const std::string&)> release) { release_ = std::move(release); }
  /// The running job on a session, or "".
  std::string job_on_session(const std::string& session) const;
  /// The running scan holding a scanner URI, or "".
  std::string job_on_device(const std::string& uri) const;

  /// `data_dir / name` for a valid session name (letters, digits, '.', '_', '-';
  /// not starting with '.'; at most 64), else InvalidInput.
  std::filesystem::path session_dir(const std::string& name) const;
  /// The profile file for a name ("" = default.yaml): InvalidInput unless it is a
  /// .yaml file directly in the profile folder.
  std::filesystem::path profile_path(const std::string& name) const;
  const std::filesystem::path& data_dir() const { return data_dir_; }
  const std::filesystem::path& profile_dir() const { return profile_dir_; }
  int threads() const { return threads_; }

 private:
  struct Job;
  std::shared_ptr<Job> find(const std::string& id) const;
  std::shared_ptr<Job> add(const std::string& kind, const std::string& session, const std::string& device);
  void launch(const std::shared_ptr<Job>& job, std::function<void(Job&)> work);

  std::filesystem::path data_dir_, profile_dir_;
  int threads_ = 0;
  mutable std::mutex mutex_;
  std::map<std::string, std::shared_ptr<Job>> jobs_;
  int next_id_ = 1;
  std::function<void(const std::string&)> release_;
};

/// "scheme:path" of a device URI (its options dropped): the device it names.
std::string device_key(const std::string& uri);

/// Checks a name for use as one path component under a served folder: no '/',
/// no NUL, not "." or "..", not starting with '.', at most 128 characters.
bool safe_component(const std::string& name);

}  // namespace station
