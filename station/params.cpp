#include "station/params.h"

#include "registration/registration.h"
#include "core/error.h"
#include "reconstruct/surface.h"
#include "reconstruct/wlop.h"

namespace station {

const std::vector<ProfileOption>& profile_options() {
  // Options keep the names they had where one command had them first (--epsilon for
  // epsilon0, --colour for colour_method); `reconstruct --holes close|open` became
  // --hole close|keep, the profile's and `run`'s spelling.
  static const std::vector<ProfileOption> options = [] {
    std::vector<ProfileOption> o;
    const auto value = [&](const char* key, const char* cmd, const char* opt, const char* help,
                           std::vector<std::string> choices = {}, std::vector<std::string> implies = {}) {
      o.push_back({key, cmd, opt, "", help, std::move(choices), std::move(implies)});
    };
    const auto flag = [&](const char* key, const char* cmd, const char* opt, const char* to, const char* help) {
      o.push_back({key, cmd, opt, to, help, {}, {}});
    };
    // station reconstruct: the surface stage on a cloud.
    value("reconstruct.resolution", "reconstruct", "--resolution",
          "grid cells along the longest side: auto (from the points' spacing) or 8..2048 (up to 4096 with --blocks "
          "or --max-memory)");
    value("reconstruct.extractor", "reconstruct", "--extractor",
          "dmc: Deformed Marching Cubes (thin parts, sharp edges; docs/dmc.md) or mc: plain marching cubes",
          {"dmc", "mc"});
    value("reconstruct.hole", "reconstruct", "--hole",
          "where there is no data: auto (close a cloud that encloses a volume, keep a one-sided patch open), "
          "close (smooth, watertight) or keep (left open)",
          {"auto", "close", "keep"});
    value("reconstruct.epsilon0", "reconstruct", "--epsilon",
          "MPU fit tolerance epsilon_0, relative to the unit-diagonal box (0: from the cloud's noise level, at "
          "least the paper's 1e-4)");
    flag("reconstruct.colour", "reconstruct", "--no-colour", "false", "do not colour the mesh from the input's colours");
    value("reconstruct.colour_method", "reconstruct", "--colour",
          "mpu: the MPU colour function (sharp colour boundaries; docs/colour.md) or nearest: k-NN transfer",
          {"mpu", "nearest"});
    flag("reconstruct.colour_multi", "reconstruct", "--colour-multi", "true",
         "colour function: three or more colours per cell (sharp junctions)");
    flag("reconstruct.colour_noise_robust", "reconstruct", "--colour-noise-robust", "true",
         "colour function: a boundary only between well-separated colour clusters");
    flag("reconstruct.colour_edges", "reconstruct", "--no-colour-edges", "false",
         "keep the extracted faces: do not split edges at colour boundaries (then a face that a boundary "
         "crosses blends both colours)");
    value("reconstruct.min_component", "reconstruct", "--min-component",
          "drop mesh pieces smaller than this fraction of the largest piece's area (0 keeps all)");
    flag("reconstruct.winding_close", "reconstruct", "--no-winding-close", "false",
         "with --hole close: far from the data, inside and outside by MPU's extrapolation instead of the "
         "cloud's winding number");
    flag("reconstruct.table_plane", "reconstruct", "--no-table-plane", "false",
         "with --up: do not close the underside flat at the table plane");
    // station run: the whole job (any key with --set; these have a shorthand).
    value("reconstruct.blocks", "reconstruct", "--blocks",
          "the surface stage in blocks of one lattice, stitched vertex for vertex: 1 (one piece), auto (a block "
          "per 500k points, at least 4 a rank) or a count; spread over the ranks under mpirun (docs/blocks.md)");
    value("reconstruct.max_memory_gb", "reconstruct", "--max-memory",
          "memory per rank in GB for the blocks: the fewest blocks that fit it (or --blocks checked against "
          "it); a run that cannot fit says so before it starts; 0: no bound");
    value("reconstruct.surface", "run", "--surface", "surface method", {"mpu", "sdm"});
    flag("reconstruct.snap_to_scans", "run", "--snap-to-scans", "true",
         "after consolidation, move the mesh's vertices onto local fits of the scans where a held-out half of "
         "them says that brings the mesh closer (the default; docs/run.md)");
    flag("reconstruct.snap_to_scans", "run", "--no-snap-to-scans", "false",
         "leave the mesh on the surface fitted to the consolidated points");
    for (const char* cmd : {"reconstruct", "run"})
      value("reconstruct.snap_significance", cmd, "--snap-significance",
            "with the snap to the scans (run) or --scans (reconstruct): a vertex moves only by the part of its "
            "fit's height beyond this many standard errors (0: all of it; the held-out check already keeps "
            "noise out)");
    value("reconstruct.max_memory_gb", "run", "--max-memory",
          "memory per rank in GB for the surface stage's blocks (0: no bound; docs/blocks.md)");
    value("reconstruct.blocks", "run", "--blocks",
          "the surface stage in blocks of one lattice: 1 (one piece), auto (a block per 500k points, at least 4 a rank) or a count "
          "(docs/blocks.md)");
    value("reconstruct.hole", "run", "--hole",
          "unseen underside: auto (close an object, keep a one-sided patch open), close (smooth, watertight) or "
          "keep (left open where there is no data)",
          {"auto", "close", "keep"});
    value("reconstruct.extractor", "run", "--extractor", "mesh extraction", {"dmc", "mc"});
    value("reconstruct.resolution", "run", "--resolution",
          "grid cells along the longest side: auto (from the points' spacing) or 8..2048 (up to 4096 with --blocks "
          "or --max-memory)");
    // station consolidate.
    value("consolidate.points", "consolidate", "--points",
          "output point count |I|: auto (ratio x input, 20000..100000) or a count (0: ratio x input)");
    value("consolidate.ratio", "consolidate", "--ratio",
          "output points as a fraction of the input, (0, 1] (instead of --points)", {}, {"consolidate.points=0"});
    value("consolidate.method", "consolidate", "--method", "wlop or edge-wlop (keeps sharp edges)",
          {"wlop", "edge-wlop"});
    value("consolidate.iterations", "consolidate", "--iterations", "iterations k (1..1000)");
    value("consolidate.radius", "consolidate", "--radius", "support radius h in input units (0 = 4 d_bb / sqrt(|J|))");
    value("consolidate.attraction", "consolidate", "--attraction",
          "projection: onto plane fits of the input (denoises and evens; docs/consolidation.md) or l1: "
          "eq. 2 / eq. 19 as the paper prints them",
          {"projection", "l1"});
    value("consolidate.fit_radius", "consolidate", "--fit-radius",
          "projection's fit radius in input units (0 = max(1.5 x the default h, 4.5 x the noise estimate))");
    value("consolidate.repulsion", "consolidate", "--repulsion",
          "with --attraction l1, wlop's repulsion: tangential (no part along the local normal: less drift off "
          "the surface) or full (as printed)",
          {"full", "tangential"});
    value("consolidate.repulsion_weight", "consolidate", "--repulsion-weight",
          "the repulsion's beta: original (theta / r, WLOP's own: close pairs separate) or printed (-theta, "
          "eq. 5 as the paper prints it)",
          {"original", "printed"});
    value("consolidate.seed", "consolidate", "--seed", "seed of the initial subset");
    value("consolidate.blocks", "consolidate", "--blocks",
          "WLOP in blocks, each at the whole cloud's scale: auto (a block per 2 M input points), 1 (one piece) or a "
          "count; over the ranks under mpirun (docs/blocks.md)");
    value("consolidate.blocks", "run", "--consolidate-blocks",
          "the consolidation in blocks: auto (a block per 2 M merged points), 1 (one piece) or a count (docs/blocks.md)");
    // station register.
    value("register.objective", "register", "--objective",
          "ICP objective; colored needs coloured views", registration_objectives());
    flag("register.global", "register", "--no-global", "false",
         "no global registration by features: views without an angle or pose fail");
    flag("register.check_angles", "register", "--no-angle-check", "false", "trust the commanded turntable angles");
    flag("register.prior_check", "register", "--no-prior-check", "false",
         "do not compare with a registration without angles when the angles mislead the run");
    value("register.rigid_turntable", "register", "--rigid-turntable",
          "hold the views on one rigid turntable axis: auto (when it fits the free poses), on, off",
          {"auto", "on", "off"});
    flag("register.fuse", "register", "--fuse", "true",
         "average overlapping points of different views in the merge (within register.fuse_distance)");
    // station scan.
    value("capture.views", "scan", "--views", "views over 360 degrees (1..3600)");
    return o;
  }();
  return options;
}

const std::vector<ProfileOnlyKey>& profile_only_keys() {
  static const std::vector<ProfileOnlyKey> keys = {
      {"capture.start_deg", "bench set-up: the plan of a scan, kept in the session"},
      {"capture.step_deg", "bench set-up: the plan of a scan, kept in the session"},
      {"capture.settle_s", "bench set-up: depends on the turntable and the object"},
      {"capture.crop", "bench set-up"},
      {"capture.volume.radius", "bench set-up: the working volume"},
      {"capture.volume.max_height", "bench set-up: the working volume"},
      {"capture.volume.table_clearance", "bench set-up: the working volume"},
      {"register.neighbors", "tuning of the pose graph; rarely changed"},
      {"register.rounds", "tuning of the pose graph; rarely changed"},
      {"register.loop_closure", "tuning of the pose graph; rarely changed"},
      {"register.voxel_rel", "tuning of the registration copies; rarely changed"},
      {"register.fuse_distance", "goes with --fuse; the default (the views' spacing) suits most scans"},
      {"consolidate.enabled", "a stage switch of station run (station consolidate always consolidates)"},
      {"sdm.level", "station run's SDM surface; station fit takes --template icosphere:L"},
      {"threads", "every command takes --threads (0..1024)"},
      {"scanner.uri", "station scan --scanner URI replaces the device with its options"},
      {"turntable.uri", "station scan --turntable URI replaces the device with its options"},
      {"scanner.options.*", "device options: station scan --set key=value"},
      {"turntable.options.*", "device options: station scan --set key=value"},
  };
  return keys;
}

WlopParams wlop_params(const PipelineConfig& pipeline, int threads) {
  const auto& c = pipeline.consolidate;
  WlopParams p;
  p.method = c.method == "edge-wlop" ? WlopMethod::kEdgeWlop : WlopMethod::kWlop;
  p.target_points = c.points_auto ? 0 : c.points;
  p.ratio = c.ratio;
  if (c.points_auto) {
    p.min_points = kAutoPointsMin;
    p.max_points = kAutoPointsMax;
  }
  p.iterations = c.iterations;
  p.radius = c.radius;
  p.seed = c.seed;
  p.attraction = c.attraction == "l1" ? WlopAttraction::kL1 : WlopAttraction::kProjection;
  p.fit_radius = c.fit_radius;
  p.repulsion = c.repulsion == "tangential" ? WlopRepulsion::kTangential : WlopRepulsion::kFull;
  p.repulsion_weight = c.repulsion_weight == "printed" ? RepulsionWeight::kPrinted : RepulsionWeight::kOriginal;
  p.threads = threads;
  return p;
}

SurfaceParams surface_params(const PipelineConfig& pipeline, int threads) {
  const auto& c = pipeline.reconstruct;
  SurfaceParams p;
  p.epsilon0 = c.epsilon0;
  p.resolution = c.resolution;
  p.extractor = c.extractor == "dmc" ? Extractor::kDmc : Extractor::kMarchingCubes;
  p.hole = c.hole == "keep" ? HoleMode::kKeep : c.hole == "close" ? HoleMode::kClose : HoleMode::kAuto;
  p.winding_close = c.winding_close;
  p.colour = c.colour;
  p.colour_method = c.colour_method == "nearest" ? ColourMethod::kNearest : ColourMethod::kMpu;
  p.colour_multi = c.colour_multi;
  p.colour_noise_robust = c.colour_noise_robust;
  p.colour_edges = c.colour_edges;
  p.min_component = c.min_component;
  p.snap_significance = c.snap_significance;
  p.threads = threads;
  return p;
}

RegistrationParams registration_params(const PipelineConfig& p) {
  RegistrationParams r;
  r.neighbors = p.reg.neighbors;
  r.rounds = p.reg.rounds;
  r.loop_closure = p.reg.loop_closure;
  r.voxel_rel = p.reg.voxel_rel;
  r.global_registration = p.reg.global;
  r.check_angles = p.reg.check_angles;
  r.prior_check = p.reg.prior_check;
  r.rigid_turntable = parse_rigid_turntable(p.reg.rigid_turntable);
  r.fuse = p.reg.fuse;
  r.fuse_distance = p.reg.fuse_distance;
  IcpObjective o = IcpObjective::kPointToPlane;
  if (p.reg.objective == "symmetric") o = IcpObjective::kSymmetric;
  else if (p.reg.objective == "point-to-point") o = IcpObjective::kPointToPoint;
  else if (p.reg.objective == "colored") o = IcpObjective::kColoured;
  else if (p.reg.objective == "generalized") o = IcpObjective::kGeneralized;
  else if (p.reg.objective != "point-to-plane")
    throw InvalidInput("register.objective: unknown objective '" + p.reg.objective + "'");
  r.icp.objective = o;
  r.final_objective = o;
  return r;
}

const char* wlop_label(const std::string& method) { return method == "edge-wlop" ? "edge-WLOP" : "WLOP"; }


}  // namespace station
