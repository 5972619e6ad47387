// `station reconstruct --blocks` (issue 29): in sequence and over two MPI ranks
// (mpirun --oversubscribe -n 2, loopback), the blocked mesh is the single run's
// within half a cell, with no cracks or doubled faces at the seams; --resume takes
// up the blocks an interrupted run left.
#include <gtest/gtest.h>

#include <cstdlib>
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <regex>
#include <string>

#include "core/io.h"
#include "core/mesh_topology.h"
#include "eval/eval.h"
#include "test_util.h"

namespace station {
namespace {

namespace fs = std::filesystem;

std::string station_cmd() { return std::string(STATION_BINARY); }

double json_number(const std::string& json, const std::string& key) {
  std::smatch m;
  const std::regex re("\"" + key + "\":([-0-9.eE+]+)");
  if (!std::regex_search(json, m, re)) return -1;
  return std::stod(m[1]);
}

double hausdorff(const Mesh& a, const Mesh& b) {
  EvalParams ep;
  ep.mesh_samples = 60000;
  ep.threads = 2;
  return evaluate(a, b, ep).hausdorff;
}

class BlocksCli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TempDir("station-blocks");
    const Mesh bottle = read_mesh(test::source_dir() / "data/mustard_bottle/textured.obj");
    write_ply(*dir_ / "bottle.ply", sample_mesh(bottle, 200000, 11));
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }
  static std::string path(const std::string& name) { return (*dir_ / name).string(); }
  static std::string reconstruct(const std::string& out, const std::string& extra) {
    return "reconstruct " + path("bottle.ply") + " -o " + out + " --resolution 160 --no-colour --json " + extra;
  }
  // The command prefix for two ranks on this machine (root allowed: CI runs as root).
  static std::string mpirun2() {
    setenv("OMPI_ALLOW_RUN_AS_ROOT", "1", 1);
    setenv("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1", 1);
    return "mpirun --oversubscribe -n 2 " + station_cmd();
  }
  static test::TempDir* dir_;
};
test::TempDir* BlocksCli::dir_ = nullptr;

TEST_F(BlocksCli, BlocksInSequenceAndOverTwoRanksAreTheSingleMesh) {
  const auto single = test::run_command(station_cmd() + " " + reconstruct(path("single.ply"), "--threads 2"));
  ASSERT_EQ(single.code, 0) << single.out;
  const auto seq = test::run_command(station_cmd() + " " + reconstruct(path("seq.ply"), "--threads 2 --blocks 8"));
  ASSERT_EQ(seq.code, 0) << seq.out;
  EXPECT_EQ(json_number(seq.out, "blocks"), 8);
  EXPECT_GT(json_number(seq.out, "seam_vertices_joined"), 100);
  EXPECT_FALSE(fs::exists(path("seq.ply.blocks")));  // the work folder goes once the mesh is written
  const auto mpi = test::run_command(mpirun2() + " " +
                                     reconstruct(path("mpi.ply"), "--threads 1 --blocks 8"));
  ASSERT_EQ(mpi.code, 0) << mpi.out;
  EXPECT_EQ(json_number(mpi.out, "ranks"), 2) << mpi.out;

  const Mesh s = read_mesh(path("single.ply")), b = read_mesh(path("seq.ply")), m = read_mesh(path("mpi.ply"));
  const double cell = json_number(seq.out, "cell_size");
  ASSERT_GT(cell, 0);
  const MeshTopology ts = mesh_topology(s), tb = mesh_topology(b);
  EXPECT_TRUE(ts.closed_manifold());
  // Watertight where the single one is: no crack (boundary edge) or doubled face
  // (non-manifold edge) along the block faces.
  EXPECT_EQ(tb.boundary_edges, ts.boundary_edges);
  EXPECT_EQ(tb.nonmanifold_edges, 0);
  EXPECT_EQ(tb.nonmanifold_vertices, 0);
  EXPECT_EQ(tb.misoriented_edges, 0);
  EXPECT_EQ(tb.components, ts.components);
  const double d = hausdorff(b, s);
  std::printf("blocks vs single: Hausdorff %.3f cells; %zu / %zu faces\n", d / cell, b.faces.size(), s.faces.size());
  EXPECT_LT(d, 0.5 * cell);
  // The ranks change nothing: the same blocks, the same numbers.
  EXPECT_EQ(m.vertices.size(), b.vertices.size());
  EXPECT_EQ(m.faces.size(), b.faces.size());
  EXPECT_LT(hausdorff(m, b), 1e-3 * cell);
}

TEST_F(BlocksCli, ResumeTakesUpTheBlocksAnInterruptedRunLeft) {
  // The output cannot be written (a folder of that name): the run fails after the
  // blocks, and their files stay.
  const std::string out = path("held.ply");
  fs::create_directories(out);
  const auto first = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 4"));
  EXPECT_NE(first.code, 0) << first.out;
  ASSERT_TRUE(fs::exists(out + ".blocks/summary.bin")) << first.out;
  // Each block's points file (the input sorted into the blocks in one pass) went when
  // the block was done.
  for (const auto& e : fs::directory_iterator(out + ".blocks"))
    EXPECT_NE(e.path().filename().string().rfind("points_", 0), 0u) << e.path();
  fs::remove_all(out);
  // Resumed for another grid: refused by name, before any block runs.
  const auto other = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 8 --resume"));
  EXPECT_NE(other.code, 0) << other.out;
  EXPECT_NE(other.out.find("run again without --resume"), std::string::npos) << other.out;
  EXPECT_TRUE(fs::exists(out + ".blocks/summary.bin"));
  const auto again = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 4 --resume"));
  ASSERT_EQ(again.code, 0) << again.out;
  EXPECT_EQ(json_number(again.out, "resumed_blocks"), 4) << again.out;
  EXPECT_TRUE(mesh_topology(read_mesh(out)).closed_manifold());
  EXPECT_FALSE(fs::exists(out + ".blocks"));
}

TEST_F(BlocksCli, ADamagedBlockFileIsNamedNotTaken) {
  const std::string out = path("damaged.ply");
  fs::create_directories(out);
  const auto first = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 4"));
  EXPECT_NE(first.code, 0) << first.out;
  fs::remove_all(out);
  const fs::path piece = out + ".blocks/piece_0.bin";
  ASSERT_TRUE(fs::exists(piece)) << first.out;
  fs::resize_file(piece, fs::file_size(piece) / 2);
  const auto bad = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 4 --resume"));
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.out.find("piece_0.bin"), std::string::npos) << bad.out;
  EXPECT_FALSE(fs::exists(out));
  // Without the damaged piece that block runs again.
  fs::remove(piece);
  const auto again = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --blocks 4 --resume"));
  ASSERT_EQ(again.code, 0) << again.out;
  EXPECT_EQ(json_number(again.out, "resumed_blocks"), 3) << again.out;
  EXPECT_TRUE(mesh_topology(read_mesh(out)).closed_manifold());
}

TEST_F(BlocksCli, ResumeWithoutBlocksAndBlocksWithoutNormalsAreClearErrors) {
  const auto r = test::run_command(station_cmd() + " " + reconstruct(path("x.ply"), "--resume"));
  EXPECT_EQ(r.code, 2);  // an option without its partner: usage
  EXPECT_NE(r.out.find("--resume goes with --blocks"), std::string::npos) << r.out;
  Cloud bare = read_cloud(path("bottle.ply"));
  bare.normals.clear();
  bare.points.resize(5000);
  write_ply(path("bare.ply"), bare);
  const auto n = test::run_command(station_cmd() + " reconstruct " + path("bare.ply") + " -o " + path("y.ply") +
                                   " --blocks 4");
  EXPECT_NE(n.code, 0);
  EXPECT_NE(n.out.find("normals"), std::string::npos) << n.out;
  EXPECT_FALSE(fs::exists(path("y.ply")));
}

// A work folder that cannot be made (its parent a file here; a read-only disk alike)
// is said by its path and the file system's reason, not the library's text.
TEST_F(BlocksCli, AWorkFolderThatCannotBeMadeIsNamed) {
  const std::string parent = path("a_file");
  { std::ofstream(parent) << "x"; }
  const auto r = test::run_command(station_cmd() + " " + reconstruct(parent + "/w.ply", "--blocks 2"));
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(parent + "/w.ply.blocks: cannot make the blocks' work folder: Not a directory"), std::string::npos)
      << r.out;
  EXPECT_EQ(r.out.find("filesystem error"), std::string::npos) << r.out;
}

// The blocks' work folder (OUT.blocks) is cleared: a folder of that name that holds
// anything else, or an input inside it, is refused before anything is touched; and
// the profile given with --config is an input like the cloud.
TEST_F(BlocksCli, AWorkFolderThatIsNotTheBlocksIsNeverCleared) {
  const std::string out = path("w.ply"), work = out + ".blocks";
  fs::create_directories(work);
  { std::ofstream(work + "/notes.txt") << "mine"; }
  auto r = test::run_command(station_cmd() + " " + reconstruct(out, "--blocks 2"));
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(work + ": the blocks' work folder for this output holds notes.txt, which the blocks did not "
                              "write"),
            std::string::npos)
      << r.out;
  EXPECT_TRUE(fs::exists(work + "/notes.txt"));
  r = test::run_command(station_cmd() + " consolidate " + path("bottle.ply") + " -o " + out + " --blocks 2 --points 2000");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("holds notes.txt, which the blocks did not write"), std::string::npos) << r.out;
  EXPECT_TRUE(fs::exists(work + "/notes.txt"));
  fs::remove(work + "/notes.txt");
  // What a killed run leaves (the blocks' .part files and temporaries) is theirs.
  for (const char* leftover : {"points_0.bin.part", "wlop_points_1.bin.part", "wlop_3.ply.part.tmp-12-0", "summary.bin"})
    std::ofstream(work + "/" + leftover) << "x";
  r = test::run_command(station_cmd() + " " + reconstruct(out, "--blocks 2"));
  EXPECT_EQ(r.code, 0) << r.out;
  EXPECT_FALSE(fs::exists(work));
  fs::remove(out);
  fs::create_directories(work);
  fs::copy_file(path("bottle.ply"), work + "/cloud.ply");
  r = test::run_command(station_cmd() + " reconstruct " + work + "/cloud.ply -o " + out +
                        " --resolution 160 --no-colour --blocks 2");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(work + "/cloud.ply: inside " + work + ", the blocks' work folder for this output"),
            std::string::npos)
      << r.out;
  EXPECT_TRUE(fs::exists(work + "/cloud.ply"));
  EXPECT_FALSE(fs::exists(out));
  const std::string profile = path("profile.ply");  // (a YAML profile, named as an output could be)
  { std::ofstream(profile) << "reconstruct:\n  resolution: 64\n"; }
  r = test::run_command(station_cmd() + " reconstruct " + path("bottle.ply") + " -o " + profile + " --config " + profile);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(profile + " is also an input"), std::string::npos) << r.out;
}

// --max-memory picks the block count (and says what it expects); a bound no run can
// keep, or a --blocks count over it, is refused before any block runs.
TEST_F(BlocksCli, MaxMemoryPicksTheBlocksOrRefusesBeforeStarting) {
  const std::string out = path("bounded.ply");
  const auto ok = test::run_command(station_cmd() + " " + reconstruct(out, "--threads 2 --max-memory 0.35"));
  ASSERT_EQ(ok.code, 0) << ok.out;
  EXPECT_GT(json_number(ok.out, "blocks"), 1) << ok.out;
  const double estimate = json_number(ok.out, "memory_estimate_gb");
  EXPECT_GT(estimate, 0.26) << ok.out;
  EXPECT_LE(estimate, 0.35) << ok.out;
  EXPECT_TRUE(mesh_topology(read_mesh(out)).closed_manifold());
  const std::string none = path("unbounded.ply");
  const auto low = test::run_command(station_cmd() + " " + reconstruct(none, "--max-memory 0.26"));
  EXPECT_NE(low.code, 0);
  EXPECT_NE(low.out.find("--max-memory 0.26 GB is below"), std::string::npos) << low.out;
  const auto few = test::run_command(station_cmd() + " " + reconstruct(none, "--max-memory 0.35 --blocks 2"));
  EXPECT_NE(few.code, 0);
  EXPECT_NE(few.out.find("or more fits"), std::string::npos) << few.out;
  const auto bad = test::run_command(station_cmd() + " " + reconstruct(none, "--max-memory 0.1"));
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.out.find("--max-memory 0.1: must be"), std::string::npos) << bad.out;
  EXPECT_FALSE(fs::exists(none));
  EXPECT_FALSE(fs::exists(none + ".blocks"));
}

// `station consolidate --blocks 4` (WLOP in blocks, reconstruct/blocks_wlop.h): in
// sequence and over two ranks the same file; about the points asked for; no work
// folder left.
TEST_F(BlocksCli, ConsolidateInBlocksIsTheSameOnTwoRanks) {
  const std::string args = " consolidate " + path("bottle.ply") + " --blocks 4 --points 20000 --json -o ";
  const auto seq = test::run_command(station_cmd() + args + path("wlop_seq.ply") + " --threads 2");
  ASSERT_EQ(seq.code, 0) << seq.out;
  const auto mpi = test::run_command(mpirun2() + args + path("wlop_mpi.ply") +
                                     " --threads 1");
  ASSERT_EQ(mpi.code, 0) << mpi.out;
  EXPECT_EQ(json_number(seq.out, "blocks"), 4) << seq.out;
  EXPECT_EQ(json_number(mpi.out, "ranks"), 2) << mpi.out;
  EXPECT_LT(json_number(seq.out, "max_block_points"), 200000 * 0.6) << seq.out;
  EXPECT_NEAR(json_number(seq.out, "output_points"), 20000, 400) << seq.out;
  EXPECT_EQ(read_file_bytes(path("wlop_seq.ply")), read_file_bytes(path("wlop_mpi.ply")));
  EXPECT_FALSE(fs::exists(path("wlop_seq.ply.blocks")));
  EXPECT_FALSE(fs::exists(path("wlop_mpi.ply.blocks")));
  // A block count out of range is refused by name.
  const auto bad = test::run_command(station_cmd() + " consolidate " + path("bottle.ply") + " --blocks 0 -o " +
                                     path("wlop_bad.ply"));
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.out.find("--blocks 0"), std::string::npos) << bad.out;
}

// `mpirun -n 2 station run --consolidate-blocks 4 --blocks 4`: rank 0 runs the job,
// rank 1 joins the blocks of its consolidation and of its surface stage; the mesh is
// the one-process blocked run's.
TEST_F(BlocksCli, RunOverTwoRanksIsTheRunInOneProcess) {
  const std::string args = " run " + path("bottle.ply") +
                           " --blocks 4 --consolidate-blocks 4 --resolution 96 --no-report --json --set "
                           "consolidate.points=20000 -o ";
  const auto seq = test::run_command(station_cmd() + args + path("run_seq") + " --threads 1");
  ASSERT_EQ(seq.code, 0) << seq.out;
  const auto mpi = test::run_command(mpirun2() + args + path("run_mpi") +
                                     " --threads 1");
  ASSERT_EQ(mpi.code, 0) << mpi.out;
  EXPECT_EQ(json_number(mpi.out, "ranks"), 2) << mpi.out;
  EXPECT_EQ(json_number(seq.out, "ranks"), 1) << seq.out;
  EXPECT_EQ(json_number(mpi.out, "blocks"), 4) << mpi.out;
  EXPECT_FALSE(fs::exists(path("run_mpi") + "/surface.blocks"));
  EXPECT_FALSE(fs::exists(path("run_mpi") + "/consolidate.blocks"));
  EXPECT_EQ(read_file_bytes(path("run_seq") + "/consolidated.ply"), read_file_bytes(path("run_mpi") + "/consolidated.ply"));
  const Mesh a = read_mesh(path("run_seq") + "/mesh.ply"), b = read_mesh(path("run_mpi") + "/mesh.ply");
  EXPECT_TRUE(mesh_topology(b).closed_manifold());
  EXPECT_EQ(a.faces.size(), b.faces.size());
  const double cell = json_number(mpi.out, "cell_size");
  ASSERT_GT(cell, 0) << mpi.out;
  EXPECT_LT(hausdorff(a, b), 1e-3 * cell);
}

// The identity target on a real session: the bundled dragon (15 turntable
// scans), `station run` against `mpirun -n 2 station run --blocks 8`, closed (the
// default: the closing spans its unseen underside) and with the holes kept. Before
// 2026-12-05 the closed meshes were 1.9 cells apart where the closing fills (the
// single run's trust distance from a subset, DMC's fixed seam points), the kept ones
// 0.84 cell (MPU's balls beyond an 8-cell margin at the thinning rims).
TEST_F(BlocksCli, DragonSessionInBlocksIsTheSingleRunWithinHalfACell) {
  std::string files;
  for (int a = 0; a < 360; a += 24)
    files += " " + (test::source_dir() / ("data/dragon_stand/dragonStandRight_" + std::to_string(a) + ".ply")).string();
  const std::string session = path("dragon");
  const auto imp = test::run_command(station_cmd() + " import" + files + " --step 24 --stanford-conf " +
                                     (test::source_dir() / "data/dragon_stand/dragonStandRight.conf").string() + " -o " +
                                     session + " --json");
  ASSERT_EQ(imp.code, 0) << imp.out;
  for (const std::string hole : {"auto", "keep"}) {
    const std::string args = " run " + session + " --hole " + hole + " --no-report --json -o ";
    // The blocks do not snap the mesh to the scans (docs/run.md): the single run
    // compared with them does not either.
    const auto single =
        test::run_command(station_cmd() + args + path("dragon_single_" + hole) + " --threads 2 --no-snap-to-scans");
    ASSERT_EQ(single.code, 0) << single.out;
    const auto blocks = test::run_command(mpirun2() + args +
                                          path("dragon_blocks_" + hole) + " --blocks 8 --threads 1");
    ASSERT_EQ(blocks.code, 0) << blocks.out;
    const Mesh a = read_mesh(path("dragon_single_" + hole) + "/mesh.ply"),
               b = read_mesh(path("dragon_blocks_" + hole) + "/mesh.ply");
    const double cell = json_number(single.out, "cell_size");
    ASSERT_GT(cell, 0) << single.out;
    const MeshTopology ta = mesh_topology(a), tb = mesh_topology(b);
    if (hole == "auto") {
      EXPECT_TRUE(tb.closed_manifold() && ta.closed_manifold());
    }
    EXPECT_EQ(tb.nonmanifold_edges, 0) << hole;
    const double d = hausdorff(a, b);
    std::printf("dragon, --hole %s: blocks vs single Hausdorff %.3f cells; %zu / %zu faces\n", hole.c_str(), d / cell,
                b.faces.size(), a.faces.size());
    EXPECT_LT(d, 0.5 * cell) << hole;
  }
}

// `station run --batch`: the sessions of a list over two ranks, a failing one named
// in the table without stopping the others, exit 3.
TEST_F(BlocksCli, BatchRunsEverySessionOfTheListAndTabulatesThem) {
  Cloud small = read_cloud(path("bottle.ply"));
  small.points.resize(30000);
  small.normals.resize(30000);
  if (!small.colours.empty()) small.colours.resize(30000);
  write_ply(path("small.ply"), small);
  {
    std::ofstream list(path("batch.txt"));
    list << "# three sessions\nsmall.ply\n\n" << path("small.ply") << "\nmissing_session\n";
  }
  const auto r = test::run_command(mpirun2() + " run --batch " +
                                   path("batch.txt") + " -o " + path("batch_out") +
                                   " --resolution 64 --no-report --threads 1 --set consolidate.points=5000");
  EXPECT_EQ(r.code, 3) << r.out;
  const std::string table = read_file_bytes(path("batch_out") + "/batch.tsv");
  EXPECT_EQ(std::count(table.begin(), table.end(), '\n'), 4) << table;  // a header and three sessions
  EXPECT_NE(table.find("\tok\t"), std::string::npos) << table;
  EXPECT_NE(table.find("missing_session\tfailed\t"), std::string::npos) << table;
  EXPECT_TRUE(fs::exists(path("batch_out") + "/small/mesh.ply"));
  EXPECT_TRUE(fs::exists(path("batch_out") + "/small_2/mesh.ply"));
  EXPECT_FALSE(fs::exists(path("batch_out") + "/.batch"));
  EXPECT_NE(r.out.find("2 ranks, 1 failed"), std::string::npos) << r.out;
  const auto none = test::run_command(station_cmd() + " run -o " + path("x"));
  EXPECT_NE(none.code, 0);
  EXPECT_NE(none.out.find("--batch LIST"), std::string::npos) << none.out;
}

}  // namespace
}  // namespace station
