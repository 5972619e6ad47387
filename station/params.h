#pragma once
// One parameter vocabulary (docs/parameters.md): a profile key
// (config/default.yaml, "section.key"), the command-line option that sets it, and
// the library's params struct it maps into, all in one place. A command-line
// option is an override of its profile key ("--resolution 192" is
// "--set reconstruct.resolution=192"), checked by the profile's own rules, so a
// command and `station run` given the same profile build the same result.
#include <string>
#include <vector>

#include "station/config.h"

namespace station {

struct WlopParams;
struct SurfaceParams;
struct RegistrationParams;

/// A command-line option that sets a profile key.
struct ProfileOption {
  std::string key;      ///< "reconstruct.resolution"
  std::string command;  ///< the subcommand that has it ("reconstruct", "run", "consolidate", ...)
  std::string option;   ///< "--resolution"
  /// Empty: the option takes the key's value. Else a flag that sets the key to this.
  std::string flag_value;
  std::string help;
  std::vector<std::string> choices;  ///< allowed values (empty: any the profile accepts)
  /// Further overrides a given option implies (--ratio also sets consolidate.points=0).
  std::vector<std::string> implies;
};

/// Every command-line option that stands for a profile key, by command.
const std::vector<ProfileOption>& profile_options();

/// Profile keys with no command-line option of their own (set them in a profile, or
/// with --set section.key=value where the command takes --set), and why.
struct ProfileOnlyKey {
  std::string key;
  std::string why;
};
const std::vector<ProfileOnlyKey>& profile_only_keys();

/// The profile's consolidate section as the library's parameters.
WlopParams wlop_params(const PipelineConfig& pipeline, int threads);
/// The profile's reconstruct section as the surface stage's parameters (table_up,
/// note and resolution_name are the caller's).
SurfaceParams surface_params(const PipelineConfig& pipeline, int threads);
/// The registration parameters of a profile's `register` section (station run,
/// station register and station calibrate turntable).
RegistrationParams registration_params(const PipelineConfig& pipeline);

/// How progress lines name a consolidation method ("edge-wlop" | "wlop").
const char* wlop_label(const std::string& method);


}  // namespace station
