// Every shipped profile (config/*.yaml) loads, and its device options are ones
// the drivers accept (the devices are made from the URIs, not opened).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <map>
#include <regex>
#include <string>
#include <vector>

#include "core/error.h"
#include "drivers/real_devices.h"
#include "drivers/registry.h"
#include "sim/sim.h"
#include "station/config.h"
#include "station/params.h"
#include "registration/registration.h"
#include "core/io.h"
#include "reconstruct/surface.h"
#include "reconstruct/wlop.h"
#include "test_util.h"

namespace station {
namespace {

namespace fs = std::filesystem;

TEST(Profiles, EveryShippedProfileLoadsAndNamesDevicesTheDriversAccept) {
  int n = 0;
  for (const auto& e : fs::directory_iterator(test::source_dir() / "config")) {
    if (e.path().extension() != ".yaml") continue;
    ++n;
    SCOPED_TRACE(e.path().string());
    StationConfig cfg;
    ASSERT_NO_THROW(cfg = load_config(e.path()));
    DeviceRegistry reg;
    register_sim_devices(reg);
    register_real_devices(reg);
    EXPECT_NO_THROW(reg.make_scanner(compose_uri(cfg.scanner_uri, cfg.scanner_options)));
    EXPECT_NO_THROW(reg.make_turntable(compose_uri(cfg.turntable_uri, cfg.turntable_options)));
  }
  EXPECT_GE(n, 3);  // default + one per real bench kind
}

TEST(Profiles, AWrongDeviceOptionIsCaughtByTheDriver) {
  DeviceRegistry reg;
  register_real_devices(reg);
  EXPECT_THROW(reg.make_turntable("horus:/dev/ttyUSB0?steps=200&stepz=3"), DeviceError);
  EXPECT_THROW(reg.make_scanner("v4l2:auto?fx=1&fy=1&cx=1&cy=1&distortion=1"), DeviceError);
}


// The leaf keys of a profile file, dotted ("reconstruct.resolution"), read by
// indentation (the shipped profiles are plain block YAML).
std::vector<std::string> profile_keys(const fs::path& file) {
  std::ifstream in(file);
  std::vector<std::pair<std::size_t, std::string>> stack;  // (indent, name)
  std::vector<std::string> keys;
  const std::regex line_re(R"(^( *)([A-Za-z_][A-Za-z0-9_]*):\s*([^#]*?)\s*(#.*)?$)");
  for (std::string line; std::getline(in, line);) {
    std::smatch m;
    if (!std::regex_match(line, m, line_re)) continue;
    const std::size_t indent = m[1].length();
    while (!stack.empty() && stack.back().first >= indent) stack.pop_back();
    std::string key;
    for (const auto& [i, name] : stack) key += name + ".";
    key += m[2].str();
    if (m[3].length() == 0) {
      stack.emplace_back(indent, m[2].str());  // a section
    } else {
      keys.push_back(key);
    }
  }
  return keys;
}

bool is_profile_only(const std::string& key) {
  for (const ProfileOnlyKey& p : profile_only_keys()) {
    if (p.key == key) return true;
    if (p.key.size() > 2 && p.key.compare(p.key.size() - 2, 2, ".*") == 0 &&
        key.rfind(p.key.substr(0, p.key.size() - 1), 0) == 0)
      return true;
  }
  return false;
}

std::string help_of(const std::string& command) {
  return test::run_command(std::string(STATION_BINARY) + " " + command + " --help").out;
}

// One vocabulary (station/params.h, docs/parameters.md): every key of the default
// profile has a command-line option or is documented as profile-only; every option
// in the table names a real key, is in its command's --help, and is documented.
TEST(Profiles, EveryKeyHasItsOptionOrIsDocumentedAsProfileOnly) {
  const std::vector<std::string> keys = profile_keys(test::source_dir() / "config/default.yaml");
  ASSERT_GT(keys.size(), 40u);
  const std::string doc = read_file_bytes(test::source_dir() / "docs/parameters.md");
  std::map<std::string, std::string> helps;
  for (const std::string& key : keys) {
    bool has_option = false;
    for (const ProfileOption& o : profile_options()) has_option |= o.key == key;
    EXPECT_TRUE(has_option || is_profile_only(key)) << key << ": no command-line option and not profile-only";
    EXPECT_FALSE(has_option && is_profile_only(key)) << key << ": both an option and profile-only";
  }
  for (const ProfileOption& o : profile_options()) {
    EXPECT_NE(std::find(keys.begin(), keys.end(), o.key), keys.end()) << o.option << ": no profile key " << o.key;
    if (!helps.count(o.command)) helps[o.command] = help_of(o.command);
    EXPECT_NE(helps[o.command].find(o.option), std::string::npos) << o.command << " --help lacks " << o.option;
    EXPECT_NE(doc.find("`" + o.option + "`"), std::string::npos) << "docs/parameters.md lacks " << o.option;
    EXPECT_NE(doc.find("`" + o.key + "`"), std::string::npos) << "docs/parameters.md lacks " << o.key;
  }
  for (const ProfileOnlyKey& p : profile_only_keys()) {
    EXPECT_NE(doc.find("`" + p.key + "`"), std::string::npos) << "docs/parameters.md lacks " << p.key;
    EXPECT_FALSE(p.why.empty()) << p.key;
  }
}

// One default everywhere: the built-in defaults (no profile) are the default
// profile's values, so a command given no --config and no profile file agree.
TEST(Profiles, BuiltInDefaultsAreTheDefaultProfile) {
  const PipelineConfig a = load_config(fs::path()).pipeline;
  const PipelineConfig b = load_config(test::source_dir() / "config/default.yaml").pipeline;
  const WlopParams wa = wlop_params(a, 0), wb = wlop_params(b, 0);
  EXPECT_EQ(int(wa.method), int(wb.method));
  EXPECT_EQ(wa.target_points, wb.target_points);
  EXPECT_EQ(wa.ratio, wb.ratio);
  EXPECT_EQ(wa.iterations, wb.iterations);
  EXPECT_EQ(wa.radius, wb.radius);
  EXPECT_EQ(wa.seed, wb.seed);
  EXPECT_EQ(int(wa.repulsion), int(wb.repulsion));
  EXPECT_EQ(int(wa.repulsion_weight), int(wb.repulsion_weight));
  const SurfaceParams sa = surface_params(a, 0), sb = surface_params(b, 0);
  EXPECT_EQ(sa.epsilon0, sb.epsilon0);
  EXPECT_EQ(sa.resolution, sb.resolution);
  EXPECT_EQ(int(sa.extractor), int(sb.extractor));
  EXPECT_EQ(int(sa.hole), int(sb.hole));
  EXPECT_EQ(sa.winding_close, sb.winding_close);
  EXPECT_EQ(sa.colour, sb.colour);
  EXPECT_EQ(int(sa.colour_method), int(sb.colour_method));
  EXPECT_EQ(sa.colour_multi, sb.colour_multi);
  EXPECT_EQ(sa.colour_noise_robust, sb.colour_noise_robust);
  EXPECT_EQ(sa.colour_edges, sb.colour_edges);
  EXPECT_EQ(sa.min_component, sb.min_component);
  EXPECT_EQ(a.reconstruct.surface, b.reconstruct.surface);
  EXPECT_EQ(a.reconstruct.table_plane, b.reconstruct.table_plane);
  EXPECT_EQ(a.consolidate.enabled, b.consolidate.enabled);
  EXPECT_EQ(a.sdm.level, b.sdm.level);
  const RegistrationParams ra = registration_params(a), rb = registration_params(b);
  EXPECT_EQ(ra.neighbors, rb.neighbors);
  EXPECT_EQ(ra.rounds, rb.rounds);
  EXPECT_EQ(ra.loop_closure, rb.loop_closure);
  EXPECT_EQ(ra.voxel_rel, rb.voxel_rel);
  EXPECT_EQ(ra.global_registration, rb.global_registration);
  EXPECT_EQ(ra.check_angles, rb.check_angles);
  EXPECT_EQ(int(ra.rigid_turntable), int(rb.rigid_turntable));
  EXPECT_EQ(ra.fuse, rb.fuse);
  EXPECT_EQ(ra.fuse_distance, rb.fuse_distance);
  EXPECT_EQ(int(ra.icp.objective), int(rb.icp.objective));
}
}  // namespace
}  // namespace station
