#pragma once
// Station profiles (config/*.yaml). Every key is documented in config/default.yaml.
#include <cstddef>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "capture/capture.h"
#include "drivers/scanner.h"

namespace station {

/// Parameters of `station run`'s stages (profile sections register, consolidate,
/// reconstruct, sdm; documented in config/default.yaml).
/// consolidate.points: auto: the consolidation keeps ratio x input points, at least
/// kAutoPointsMin (or the whole input) and at most kAutoPointsMax. Measured on the
/// real dragon session (469k points; docs/run.md, issue 32): mesh -> scans with
/// holes kept 0.54 mm at 20,000 points, 0.40 at 60,000, 0.34 at 100,000; beyond
/// that the consolidation's time grows with no end-to-end gain worth it.
inline constexpr std::size_t kAutoPointsMin = 20000;
inline constexpr std::size_t kAutoPointsMax = 100000;

/// reconstruct.resolution in one piece (no blocks): at most this many cells. One piece
/// holds the whole mesh, whose faces grow with the square of the resolution: at 2048
/// cells an object that fills its box makes about 33 M faces and needs 4-5 GB, a quarter
/// of the 131 M faces and 16.7 GB measured at 4096 (reconstruct/surface.h,
/// kExtractionBytesPerFace), which ran machines out of memory with no word of the option.
/// Finer, up to 4096, in blocks (reconstruct.blocks or max_memory_gb; docs/blocks.md).
inline constexpr int kMaxOnePieceResolution = 2048;

struct PipelineConfig {
  struct Register {
    int neighbors = 2;          ///< pair each view with the next N views
    int rounds = 3;             ///< ICP + pose-graph rounds
    bool loop_closure = true;   ///< pair the last view with the first
    double voxel_rel = 0.004;   ///< registration copy voxel, relative to the view size
    /// ICP objective of every round: point-to-plane | symmetric | point-to-point |
    /// colored (Park 2017; needs colours) | generalized (Segal 2009).
    std::string objective = "point-to-plane";
    bool global = true;         ///< global registration (FPFH + RANSAC) for views without a pose
    bool check_angles = true;   ///< detect wrong commanded angles and recover them globally
    /// When the prior misleads the run: compare with the prior-free and the corrected
    /// prior's registrations and keep the better (docs/registration.md, "A wrong prior").
    bool prior_check = true;
    /// Views with an angle on one rigid turntable in the pose graph: auto (kept
    /// when it fits the free solution), on, off (capture/registration.h).
    std::string rigid_turntable = "auto";
    bool fuse = false;          ///< average overlapping points of different views in the merge
    double fuse_distance = 0;   ///< metres; 0: the views' median point spacing
  } reg;
  struct Consolidate {
    bool enabled = true;
    std::string method = "edge-wlop";  ///< edge-wlop | wlop (docs/consolidation.md)
    /// Output points: auto (points_auto: ratio x input, within kAutoPointsMin..kAutoPointsMax),
    /// a count, or 0: ratio x input.
    bool points_auto = true;
    std::size_t points = 0;
    double ratio = 0.2;
    int iterations = 35;
    double radius = 0;            ///< support radius h, input units; 0 = 4 d_bb / sqrt(|J|)
    unsigned seed = 1;
    /// l1 (eq. 2 / eq. 19 as printed; the run's default: its meshes are closer to the
    /// scans, docs/consolidation.md) | projection (onto local plane fits: denoises and
    /// evens the points; reconstruct/wlop.h WlopAttraction, the library's default)
    std::string attraction = "l1";
    double fit_radius = 0;        ///< projection's fit radius r_f, input units; 0 = from spacing and noise
    /// wlop's repulsion with attraction l1: full (eq. 1 as printed) | tangential (no part
    /// along the local normal: less drift off the surface; reconstruct/wlop.h WlopRepulsion)
    std::string repulsion = "tangential";
    /// E2's beta: original (theta / r, WLOP's own) | printed (-theta, eq. 5 as printed;
    /// reconstruct/wlop.h RepulsionWeight)
    std::string repulsion_weight = "original";
    /// In blocks (reconstruct/blocks_wlop.h, docs/blocks.md): 0 = auto (a block per 2 M
    /// input points: smaller clouds in one piece), 1 = one piece, else about that many;
    /// over the ranks under mpirun.
    int blocks = 0;
  } consolidate;
  struct Reconstruct {
    std::string surface = "mpu";    ///< mpu | sdm
    int resolution = 0;             ///< cells along the longest side; 0 = auto (from the points' spacing)
    double epsilon0 = 0;            ///< MPU tolerance; 0 = from the cloud's noise
    std::string extractor = "dmc";  ///< dmc | mc
    std::string hole = "auto";      ///< auto | close | keep (the unseen underside)
    /// With hole close on a session (turntable axis known): no surface below the
    /// lowest point along the axis, so the underside closes flat on the table.
    bool table_plane = true;
    /// With hole close: far from the data (beyond a few point spacings) the solid is
    /// decided by the winding number of the oriented cloud, not MPU's extrapolation
    /// (reconstruct/winding_close.h).
    bool winding_close = true;
    bool colour = true;             ///< colour the mesh when the cloud has colours
    std::string colour_method = "mpu";  ///< mpu (colour function) | nearest (k-NN transfer)
    bool colour_multi = false;      ///< colour function: 3+ colours per cell (junctions)
    bool colour_noise_robust = false;  ///< colour function: no boundaries invented by noise
    /// Split mesh edges at colour boundaries so no face blends two colours across one
    /// (reconstruct/colour_edges.h; colour_method mpu only).
    bool colour_edges = true;
    double min_component = 0.01;    ///< drop pieces below this fraction of the largest's area
    /// station run, after consolidation: the mesh's vertices move onto local fits of
    /// the scans (the cloud before consolidation; reconstruct/scan_snap.h) where a
    /// held-out half of them says so: clean, dense scans gain, noisy ones are left as
    /// they are (docs/run.md). Not with blocks.
    bool snap_to_scans = true;
    double snap_significance = 0;  ///< ScanSnapParams::significance
    /// The surface stage in blocks of one lattice (reconstruct/blocks.h, docs/blocks.md):
    /// 1 = one piece (no blocks), 0 = auto (a block per 500k points, at least 4 a rank), else about that many.
    int blocks = 1;
    /// Memory per rank for the blocks (GB): the block count that fits it is picked
    /// (or --blocks checked against it); 0 = no bound.
    double max_memory_gb = 0;
    /// The surface stage runs in blocks (a block count or a memory bound given).
    bool in_blocks() const { return blocks != 1 || max_memory_gb > 0; }
  } reconstruct;
  struct Sdm {
    int level = 5;  ///< icosphere template subdivision level
  } sdm;
};

struct StationConfig {
  std::string scanner_uri = "sim:synthetic";
  DeviceOptions scanner_options;  ///< merged into the scanner URI's query
  std::string turntable_uri = "sim:turntable";
  DeviceOptions turntable_options;
  CaptureParams capture;
  PipelineConfig pipeline;
  int threads = 0;  ///< 0 = all cores
  std::filesystem::path source;  ///< the profile file, empty for built-in defaults
};

/// Reads a profile. Relative paths in the `mesh` and `session` device options
/// resolve against the profile's folder. FormatError("FILE: key: problem").
/// `overrides` are "section.key=value" (e.g. "reconstruct.resolution=192"), applied
/// to the profile before it is validated, so they obey the same checks.
StationConfig load_config(const std::filesystem::path& path,
                          const std::vector<std::string>& overrides = {});

/// The profile used when --config is not given: config/default.yaml of the
/// source tree the binary was built from, if it is there; else built-in defaults.
std::filesystem::path default_config_path();

/// The leaf values of a profile file as dotted keys ("reconstruct.resolution" ->
/// "128"), as written there; empty when the file cannot be read (for --help).
std::map<std::string, std::string> profile_values(const std::filesystem::path& path);

/// The names `register.objective` accepts (see PipelineConfig::Register), in one
/// place for the profile check and the CLI's --objective.
const std::vector<std::string>& registration_objectives();
bool valid_registration_objective(const std::string& name);

/// "scheme:path?a=1" + {b: 2} -> "scheme:path?a=1&b=2" (options override the URI's).
std::string compose_uri(const std::string& uri, const DeviceOptions& options);

}  // namespace station
