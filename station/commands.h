#pragma once
// The station command's pieces: the options every command shares, the arguments of
// each command group and its entry points (station/cmd_*.cpp), wired up by run_cli
// (station/cli.cpp). Internal to station/.
#include <tbb/global_control.h>

#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "capture/session.h"
#include "core/error.h"
#include "drivers/registry.h"
#include "station/config.h"
#include "station/json.h"

namespace CLI {
class App;
class Validator;
}

namespace station::cli {

namespace fs = std::filesystem;

/// A bad value of a command-line option: a usage error (exit 2), as CLI11's own.
class UsageError : public InvalidInput {
 public:
  using InvalidInput::InvalidInput;
};

/// SIGINT / SIGTERM while a command works: its temporaries and the outputs it created
/// removed (remove_unfinished_outputs), "station: interrupted" on stderr, exit 130.
extern "C" void on_interrupt(int);
/// Installs on_interrupt for SIGINT and SIGTERM (again after a command's own handler).
void default_interrupt_handling();

/// Options every subcommand takes.
struct Common {
  std::string config;
  int threads = -1;
  bool json = false;
  /// Profile overrides from the command's profile options (station/params.h), in
  /// the order given, and how the user spelled each ("--resolution 5").
  std::vector<std::string> overrides;
  std::map<std::string, std::string> spelled;
};

struct ScanArgs {
  std::string out = "out/scan";
  bool resume = false;
  std::string scanner, turntable;
  std::vector<std::string> set;
  bool run = false;  ///< go on with `station run` into <session>/run
};

struct RunArgs {
  std::string in, out;
  std::string batch;  ///< --batch LIST: the sessions of a list instead of `in`
  bool resume = false, quiet = false, no_report = false;
  std::vector<std::string> set;
};

struct ImportArgs {
  std::vector<std::string> files;
  std::string out;
  std::string stanford_conf;
  double start = 0;
  double step = 0;
  bool has_step = false;
  int every = 1;
  std::string units = "m";
};

/// `station eval --points-metrics`: the consolidation metrics of A's points against
/// reference mesh B (reconstruct/consolidation_metrics.h).
struct PointsMetricsArgs {
  bool enabled = false;
  double edge_radius = 0;   ///< points within this distance of a sharp edge count (0: no edge error)
  double edge_angle = 30;   ///< degrees between face normals that make an edge sharp
};

struct RegisterArgs {
  std::string session, out, poses_out;
};

struct FitArgs {
  std::string in, out, templ = "icosphere:5", landmarks;
  bool no_colour = false;
};

struct ParameteriseArgs {
  std::string in, out, onto = "sphere", mapped;
  int control_points = 0;
};

struct ConsolidateArgs {
  std::string in, out;
};

struct ReconstructArgs {
  std::string in, out;
  /// The turntable axis in the cloud's frame, "x,y,z" (run.yaml's register figures
  /// up_x, up_y, up_z): enables the table plane. Empty: none.
  std::string up;
  /// With --blocks: blocks already done in OUT.blocks/ are not run again.
  bool resume = false;
  /// The scans the input was consolidated from (with normals): the vertices move onto
  /// local fits of them where a held-out half says so (reconstruct/scan_snap.h). Empty: none.
  std::string scans;
};

void add_common(CLI::App* cmd, Common& c);

// Checks of numeric options with plain one-line messages ("must be a whole number, 0
// or more (got -1)"), run on the text before it is converted (CLI11's own say
// "Value -1 not in range 0.000000 to 1797...").
CLI::Validator whole_number(long long lo, long long hi);
CLI::Validator number_above(double lo);           ///< finite, above lo
CLI::Validator number_in(double lo, double hi);   ///< finite, in [lo, hi]
CLI::Validator finite_number();

/// A command-line parse error as one plain line ("station: --threads: must be ...",
/// "station: unknown command 'bogus' (station --help lists them)").
std::string parse_error_line(const CLI::App& app, const std::exception& e);

/// The command's options that stand for profile keys (station/params.h): each
/// becomes an override of its key, checked by the profile's rules.
void add_profile_options(CLI::App* cmd, const std::string& command, Common& c);

/// The profile with the command's overrides: `extra` (e.g. --set's) first, then the
/// profile options', so an option beats a --set of the same key. A bad value names
/// the option as given.
StationConfig load_common(const Common& c, const std::vector<std::string>& extra = {});

std::unique_ptr<tbb::global_control> limit_threads(int threads);

/// Prints a --json summary line, with the process's peak resident memory.
void print_summary(JsonObject j);

// An output never replaces a recording: the manifest, a view file or a view's colour
// image of a session in any folder above it (all checked before the work).
void check_not_a_recording(const std::string& out);

// An output's format is checked before the work, not after it: `kind` names what is
// written ("a cloud", "a mesh"), `exts` the lower-case extensions it can be written as.
void check_output_name(const std::string& out, const char* kind, std::initializer_list<const char*> exts);

// An output never replaces an input of the same command: each output (empty: none) is
// compared with each input (same_file), before the work; the error names the file.
void check_not_an_input(const std::vector<std::string>& outputs, const std::vector<std::string>& inputs);

DeviceRegistry make_registry();

/// Every view a capture recorded is empty (check_recorded_points).
struct NoPointsRecorded : InvalidInput {
  using InvalidInput::InvalidInput;
};

/// After a capture: the views it recorded (from index `first_new`) without a point (the
/// object is not where the scanner looks: a scan of a mesh a metre across, the camera
/// inside it, recorded 10 empty views of 12 and exited 0 without a word). Returns a
/// warning naming them (empty when there are none); NoPointsRecorded when all are.
std::string check_recorded_points(const Session& session, std::size_t first_new);

/// A session a command (or a served scan job) created whose first view failed: what it
/// wrote goes again, and the folder too when it was new (`folder_existed` false). The
/// folder was new or empty, so all in it is the command's. Nothing when a view was
/// recorded, unless `empty_views_too` (NoPointsRecorded: every view it recorded is
/// empty).
void drop_unrecorded_session(const Session& session, bool folder_existed, bool empty_views_too = false);

/// Writes the turntable-merged cloud of a session next to it, when it has an axis.
JsonObject write_merged(const Session& session, const fs::path& out, bool quiet);

int cmd_devices(const Common& c);

int cmd_run(const Common& c, const RunArgs& a);

int cmd_scan(const Common& c, const ScanArgs& a);

int cmd_replay(const Common& c, const std::string& source, const std::string& out);

int cmd_import(const Common& c, const ImportArgs& a);

int cmd_eval(const Common& c, const std::string& a, const std::string& b, int samples, unsigned seed,
             const PointsMetricsArgs& pm_args);

int cmd_register(const Common& c, const RegisterArgs& a);

int cmd_calibrate_turntable(const Common& c, const std::string& session_dir, const std::string& out);

int cmd_calibrate_camera(const Common& c, const std::vector<std::string>& images, const std::string& board,
                         double square, const std::string& out);

int cmd_fit(const Common& c, const FitArgs& a);

int cmd_parameterise(const Common& c, const ParameteriseArgs& a);

int cmd_consolidate(const Common& c, const ConsolidateArgs& a);

int cmd_reconstruct(const Common& c, const ReconstructArgs& a);

// The library names the data it complains about by role ("target: 3 control points...",
// "mesh: empty", "suggest_epsilon0: 3 points..."); at the command line the message must
// name the file. A message that already names the input or the output, or an option
// ("--..."), stays as it is; one that starts with a role in `roles` names that role's
// file; any other names the input.
template <class Fn>
int naming_the_file(const std::string& in, const std::string& out, Fn&& fn,
                    const std::vector<std::pair<std::string, std::string>>& roles = {}) {
  try {
    return fn();
  } catch (const InvalidInput& e) {
    const std::string what = e.what();
    const auto names = [&](const std::string& path) { return !path.empty() && what.find(path) != std::string::npos; };
    if (what.rfind("--", 0) == 0 || names(in) || names(out)) throw;
    std::string file = in;
    for (const auto& [role, path] : roles)
      if (what.rfind(role, 0) == 0) file = path;
    if (file.empty() || names(file)) throw;
    throw InvalidInput(file + ": " + what);
  }
}

/// A subcommand and what it runs once the command line is parsed (its arguments
/// live in the closure).
struct Command {
  CLI::App* app = nullptr;
  std::function<int()> run;
};

/// Each group's subcommands, their options and their runs (station/cmd_*.cpp).
void add_capture_commands(CLI::App& app, std::vector<Command>& out);   ///< devices, scan, run, replay, import
void add_eval_commands(CLI::App& app, std::vector<Command>& out);      ///< eval
void add_register_commands(CLI::App& app, std::vector<Command>& out);  ///< register, calibrate turntable|camera
void add_surface_commands(CLI::App& app, std::vector<Command>& out);   ///< consolidate, fit, parameterise, reconstruct
void add_serve_commands(CLI::App& app, std::vector<Command>& out);     ///< serve

}  // namespace station::cli
