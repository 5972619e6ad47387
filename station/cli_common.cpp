#include "station/commands.h"

#include <sys/resource.h>
#include <tbb/global_control.h>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>
#include <algorithm>
#include <cstdlib>
#include <cerrno>
#include <cmath>
#include <limits>
#include <regex>
#include <atomic>
#include <cctype>
#include <chrono>
#include <csignal>
#include <unistd.h>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/error.h"
#include "core/io.h"
#include "core/threads.h"
#include "drivers/real_devices.h"
#include "drivers/registry.h"
#include "reconstruct/sdm.h"
#include "registration/registration.h"
#include "sim/sim.h"
#include "station/config.h"
#include "station/json.h"
#include "station/params.h"

namespace station::cli {

namespace {

bool parse_whole(const std::string& text, long long& v) {
  if (text.empty() || std::isspace(static_cast<unsigned char>(text[0]))) return false;
  char* end = nullptr;
  errno = 0;
  v = std::strtoll(text.c_str(), &end, 10);
  return errno == 0 && end && *end == 0;
}

bool parse_finite(const std::string& text, double& v) {
  if (text.empty() || std::isspace(static_cast<unsigned char>(text[0]))) return false;
  char* end = nullptr;
  v = std::strtod(text.c_str(), &end);
  return end && *end == 0 && std::isfinite(v);
}

std::string number_text(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

}  // namespace

CLI::Validator whole_number(long long lo, long long hi) {
  // A bound that is only the type's (an int's 2147483647) is named only to a value
  // beyond it, so that the message never contradicts the value.
  const bool open_above = hi >= std::numeric_limits<int>::max();
  const std::string want = open_above ? "must be a whole number, " + std::to_string(lo) + " or more"
                                      : "must be a whole number in " + std::to_string(lo) + ".." + std::to_string(hi);
  return CLI::Validator(
      [lo, hi, want, open_above](std::string& text) -> std::string {
        long long v = 0;
        const bool whole = parse_whole(text, v);
        if (whole && open_above && v > hi)
          return "must be a whole number, at most " + std::to_string(hi) + " (got " + text + ")";
        if (!whole || v < lo || v > hi) return want + " (got " + text + ")";
        return {};
      },
      "INT");
}

CLI::Validator number_above(double lo) {
  return CLI::Validator(
      [lo](std::string& text) -> std::string {
        double v = 0;
        if (!parse_finite(text, v) || !(v > lo)) return "must be a number above " + number_text(lo) + " (got " + text + ")";
        return {};
      },
      "NUMBER");
}

CLI::Validator number_in(double lo, double hi) {
  return CLI::Validator(
      [lo, hi](std::string& text) -> std::string {
        double v = 0;
        if (!parse_finite(text, v) || v < lo || v > hi)
          return "must be a number in " + number_text(lo) + ".." + number_text(hi) + " (got " + text + ")";
        return {};
      },
      "NUMBER");
}

CLI::Validator finite_number() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        double v = 0;
        if (!parse_finite(text, v)) return "must be a finite number (got " + text + ")";
        return {};
      },
      "NUMBER");
}

std::string parse_error_line(const CLI::App& app, const std::exception& e) {
  // The command as far as it was recognised: "station", "station calibrate"...
  std::string command = "station";
  const CLI::App* at = &app;
  for (bool deeper = true; deeper;) {
    deeper = false;
    for (const CLI::App* sub : at->get_subcommands())
      if (sub->parsed()) {
        command += " " + sub->get_name();
        at = sub;
        deeper = true;
        break;
      }
  }
  const std::string help = " (" + command + " --help lists them)";
  // main() puts "station: " first; the subcommand, if any, follows it.
  const std::string where = command == "station" ? "" : command.substr(8) + ": ";
  std::string what = e.what();
  std::smatch m;
  if (dynamic_cast<const CLI::ValidationError*>(&e)) return what;
  if (std::regex_match(what, m, std::regex("Could not convert: (\\S+) = (.*)")))
    return m[1].str() + ": not a valid value (got " + m[2].str() + ")";
  if (std::regex_match(what, m, std::regex("(\\S+): \\d+ required \\S+ missing")))
    return m[1].str() + ": needs a value";
  if (what == "A subcommand is required") {
    const std::vector<std::string> rest = at->remaining();
    if (!rest.empty() && !rest.front().empty() && rest.front()[0] != '-')
      return "unknown command '" + rest.front() + "'" + help;
    return where + "give a command" + help;
  }
  if (std::regex_match(what, m, std::regex("The following arguments? (?:was|were) not expected: (.*)")))
    return where + "unknown option or extra argument: " + m[1].str() + help;
  if (std::regex_match(what, m, std::regex("(.*) is required")))
    return where + m[1].str() + " is missing (" + command + " --help)";
  for (char& ch : what)
    if (ch == '\n') ch = ' ';
  return where + what;
}

void add_common(CLI::App* cmd, Common& c) {
  cmd->add_option("--config", c.config, "YAML profile (default: config/default.yaml)");
  cmd->add_option("--threads", c.threads, "worker threads (0 = all cores)")->check(whole_number(0, kMaxThreads));
  cmd->add_flag("--json", c.json, "print a one-line JSON summary on stdout");
}

void add_profile_options(CLI::App* cmd, const std::string& command, Common& c) {
  static const std::map<std::string, std::string> defaults = profile_values(default_config_path());
  for (const ProfileOption& o : profile_options()) {
    if (o.command != command) continue;
    const auto d = defaults.find(o.key);
    const std::string help = o.help + " (profile " + o.key +
                             (d != defaults.end() && o.flag_value.empty() ? "; default " + d->second : "") + ")";
    if (!o.flag_value.empty()) {
      cmd->add_flag_callback(
          o.option,
          [&c, o] {
            c.overrides.push_back(o.key + "=" + o.flag_value);
            c.spelled[c.overrides.back()] = o.option;
          },
          help);
      continue;
    }
    CLI::Option* opt = cmd->add_option_function<std::string>(
        o.option,
        [&c, o](const std::string& v) {
          c.overrides.push_back(o.key + "=" + v);
          c.spelled[c.overrides.back()] = o.option + " " + v;
          for (const std::string& i : o.implies) c.overrides.push_back(i);
        },
        help);
    if (!o.choices.empty()) opt->check(CLI::IsMember(o.choices));
  }
}

StationConfig load_common(const Common& c, const std::vector<std::string>& extra) {
  std::vector<std::string> overrides = extra;
  overrides.insert(overrides.end(), c.overrides.begin(), c.overrides.end());
  StationConfig cfg;
  try {
    cfg = load_config(c.config.empty() ? default_config_path() : fs::path(c.config), overrides);
  } catch (const InvalidInput& e) {
    const std::string what = e.what();
    for (const auto& [kv, option] : c.spelled)
      if (what.rfind("--set " + kv + ":", 0) == 0) throw UsageError(option + what.substr(6 + kv.size()));
    // A bad --set value is an option's fault: a usage error (exit 2), as README says.
    if (what.rfind("--set ", 0) == 0) throw UsageError(what);
    throw;
  }
  if (c.threads >= 0) cfg.threads = c.threads;
  return cfg;
}

std::unique_ptr<tbb::global_control> limit_threads(int threads) {
  if (threads <= 0) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                               std::size_t(threads));
}

void print_summary(JsonObject j) {
  rusage ru{};
  ::getrusage(RUSAGE_SELF, &ru);
  j.add("peak_rss_mb", double(ru.ru_maxrss) / 1024.0);
  std::printf("%s\n", j.str().c_str());
}

void check_not_a_recording(const std::string& out) {
  if (out.empty()) return;
  std::error_code ec;
  const fs::path p = fs::absolute(out, ec).lexically_normal();
  for (fs::path dir = p.parent_path();; dir = dir.parent_path()) {
    const fs::path manifest = dir / kManifestName;
    if (fs::is_regular_file(manifest, ec)) {
      bool recorded = p == manifest;
      try {
        for (const ViewRecord& v : manifest_from_yaml(read_file_bytes(manifest), manifest.string()).views)
          recorded = recorded || p == (dir / v.file).lexically_normal() ||
                     (!v.colour_image.empty() && p == (dir / v.colour_image).lexically_normal());
      } catch (const Error&) {
        // An unreadable manifest lists nothing to compare with; the manifest itself is guarded.
      }
      if (recorded)
        throw InvalidInput(out + ": part of the session recorded in " + dir.string() + "; write the output elsewhere");
    }
    if (dir.empty() || dir == dir.root_path()) break;
  }
}

void check_output_name(const std::string& out, const char* kind, std::initializer_list<const char*> exts) {
  check_not_a_recording(out);
  std::string ext = fs::path(out).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
  std::string list;
  bool named_so = false;
  for (const char* e : exts) {
    named_so = named_so || ext == e;
    list += std::string(list.empty() ? "" : " or ") + e;
  }
  if (!named_so) throw InvalidInput(out + ": " + kind + " is written as " + list + "; name the output that way");
}

void check_not_an_input(const std::vector<std::string>& outputs, const std::vector<std::string>& inputs) {
  for (std::size_t i = 0; i < outputs.size(); ++i) {
    const std::string& out = outputs[i];
    if (out.empty()) continue;
    for (const std::string& in : inputs)
      if (same_file(out, in)) throw InvalidInput(out + " is also an input; choose another output");
    for (std::size_t k = 0; k < i; ++k)
      if (same_file(out, outputs[k]))
        throw InvalidInput(out + " is named for two outputs; give each its own file");
  }
}

DeviceRegistry make_registry() {
  DeviceRegistry reg;
  register_sim_devices(reg);
  register_real_devices(reg);  // serial turntables, V4L2 cameras (drivers/real_devices.h)
  return reg;
}

JsonObject write_merged(const Session& session, const fs::path& out, bool quiet) {
  JsonObject j;
  if (!session.manifest().axis) {
    if (!quiet)
      std::fprintf(stderr, "note: %s has no turntable axis; merged cloud not written\n",
                   session.dir().c_str());
    return j.add_null("path");
  }
  MergeResult merged = merge_by_turntable(session);
  if (merged.cloud.empty()) throw InvalidInput(session.dir().string() + ": no points in any view");
  write_ply(out, merged.cloud);
  return j.add("path", out.string())
      .add("points", merged.cloud.size())
      .add("views", merged.merged_views)
      .add("skipped_views", merged.skipped_views)
      .add("colours", merged.cloud.has_colours());
}

}  // namespace station::cli
