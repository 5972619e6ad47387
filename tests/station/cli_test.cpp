// End-to-end tests of the `station` binary: the README's main job on the
// bundled sample, the dragon import/replay, and bad input at the boundary.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <sys/wait.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <random>
#include <regex>
#include <string>

#include "capture/session.h"
#include "core/io.h"
#include "core/texture.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "test_util.h"

namespace station {
namespace {

using CmdResult = test::CommandResult;

CmdResult run(const std::string& args) { return test::run_command(std::string(STATION_BINARY) + " " + args); }

double json_number(const std::string& json, const std::string& key) {
  std::smatch m;
  const std::regex re("\"" + key + "\":([-0-9.eE+]+)");
  if (!std::regex_search(json, m, re)) return -1;
  return std::stod(m[1]);
}

std::string repo(const std::string& rel) { return (test::source_dir() / rel).string(); }

TEST(Cli, HelpListsSubcommands) {
  const CmdResult r = run("--help");
  EXPECT_EQ(r.code, 0);
  for (const char* s : {"devices", "scan", "replay", "eval", "import", "run", "fit", "reconstruct", "calibrate"})
    EXPECT_NE(r.out.find(s), std::string::npos) << s;
  for (const char* s : {"devices", "scan", "replay", "eval", "import", "run", "fit", "reconstruct",
                        "consolidate", "register", "calibrate camera", "calibrate turntable"}) {
    const CmdResult h = run(std::string(s) + " --help");
    EXPECT_EQ(h.code, 0) << s;
    EXPECT_NE(h.out.find("--json"), std::string::npos) << s;
    EXPECT_NE(h.out.find("--threads"), std::string::npos) << s;
    EXPECT_NE(h.out.find("--config"), std::string::npos) << s;
  }
}

TEST(Cli, DevicesListsTheSimulator) {
  const CmdResult r = run("devices");
  EXPECT_EQ(r.code, 0);
  EXPECT_NE(r.out.find("sim:synthetic"), std::string::npos);
  EXPECT_NE(r.out.find("sim:turntable"), std::string::npos);
  EXPECT_NE(run("devices --json").out.find("\"command\":\"devices\""), std::string::npos);
}

// `station fit`: an icosphere template onto an ellipsoid's points, and bad templates.
TEST(Cli, FitDeformsATemplateOntoACloud) {
  test::TempDir dir("station-cli-fit");
  Mesh e = test::icosphere(4, 1.0);
  for (Vec3f& v : e.vertices) v = Vec3f(0.1f * v.x(), 0.06f * v.y(), 0.04f * v.z());
  write_ply(dir / "ellipsoid.ply", e.as_cloud());
  const CmdResult r = run("fit " + (dir / "ellipsoid.ply").string() + " -o " + (dir / "fit.ply").string() +
                          " --template icosphere:3 --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_EQ(json_number(r.out, "vertices"), 642);
  EXPECT_EQ(json_number(r.out, "flipped_faces"), 0);
  EXPECT_LT(json_number(r.out, "mean_distance_rel"), 0.005);
  EXPECT_EQ(read_mesh(dir / "fit.ply").vertices.size(), 642u);
  const CmdResult bad = run("fit " + (dir / "ellipsoid.ply").string() + " -o " + (dir / "x.ply").string() +
                            " --template icosphere:12");
  EXPECT_EQ(bad.code, 2);  // a bad option value: usage
  EXPECT_NE(bad.out.find("icosphere:L"), std::string::npos);
  // A template with a hole (not genus 0) is refused, naming the problem.
  Mesh open = test::icosphere(2);
  open.faces.pop_back();
  write_ply(dir / "open.ply", open);
  const CmdResult holed = run("fit " + (dir / "ellipsoid.ply").string() + " -o " + (dir / "x.ply").string() +
                              " --template " + (dir / "open.ply").string());
  EXPECT_EQ(holed.code, 1);
  EXPECT_NE(holed.out.find("template"), std::string::npos) << holed.out;
  EXPECT_FALSE(std::filesystem::exists(dir / "x.ply"));
}

// A lumpy closed mesh mapped onto the sphere: the OBJ carries 3 UVs per face, the
// sphere's colatitude in v follows the vertex's direction, faces across the seam get
// u raised past 1 rather than spanning the image, and a disc-only surface is refused.
TEST(Cli, ParameteriseWritesUvsFromTheSphere) {
  test::TempDir dir("station-cli-param");
  Mesh m = test::icosphere(3, 1.0);
  for (Vec3f& v : m.vertices) v = Vec3f(0.3f * v.x(), 0.2f * v.y(), 0.5f * v.z() * (1 + 0.2f * v.x()));
  write_ply(dir / "lumpy.ply", m);
  const CmdResult r = run("parameterise " + (dir / "lumpy.ply").string() + " -o " + (dir / "uv.obj").string() +
                          " --mapped " + (dir / "mapped.ply").string() + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_EQ(json_number(r.out, "flipped_faces"), 0);
  const TexturedMesh t = read_textured_mesh(dir / "uv.obj");
  ASSERT_EQ(t.mesh.faces.size(), m.faces.size());
  ASSERT_EQ(t.corner_uv.size(), 3 * m.faces.size());
  const Mesh mapped = read_mesh(dir / "mapped.ply");
  ASSERT_EQ(mapped.vertices.size(), m.vertices.size());
  double worst_v = 0, worst_span = 0;
  for (std::size_t f = 0; f < m.faces.size(); ++f) {
    float lo = 10, hi = -10;
    for (int k = 0; k < 3; ++k) {
      const Vec2f uv = t.corner_uv[3 * f + k];
      const Vec3f d = mapped.vertices[m.faces[f][k]].normalized();
      // v = colatitude / pi measured from +z.
      worst_v = std::max(worst_v, double(std::abs(uv.y() - std::acos(std::clamp(d.z(), -1.f, 1.f)) / float(M_PI))));
      lo = std::min(lo, uv.x());
      hi = std::max(hi, uv.x());
    }
    // Away from the poles (where u is arbitrary) a face spans a small range of u.
    const Vec3f c = (mapped.vertices[m.faces[f][0]] + mapped.vertices[m.faces[f][1]] + mapped.vertices[m.faces[f][2]]).normalized();
    if (std::abs(c.z()) < 0.9f) worst_span = std::max(worst_span, double(hi - lo));
  }
  EXPECT_LT(worst_v, 0.01);
  EXPECT_LT(worst_span, 0.2);
  // Without --json: the SDM's progress (the bundled bottle takes 14 s), then the summary.
  const CmdResult text =
      run("parameterise " + (dir / "lumpy.ply").string() + " -o " + (dir / "uv2.obj").string());
  ASSERT_EQ(text.code, 0) << text.out;
  EXPECT_NE(text.out.find("parameterise: SDM done in"), std::string::npos) << text.out;
  const CmdResult plane = run("parameterise " + (dir / "lumpy.ply").string() + " -o " + (dir / "p.obj").string() +
                              " --onto plane");
  EXPECT_EQ(plane.code, 1);
  EXPECT_NE(plane.out.find("disc"), std::string::npos) << plane.out;
  EXPECT_FALSE(std::filesystem::exists(dir / "p.obj"));
  const CmdResult ply = run("parameterise " + (dir / "lumpy.ply").string() + " -o " + (dir / "p.ply").string());
  EXPECT_EQ(ply.code, 1);
  EXPECT_NE(ply.out.find(".obj"), std::string::npos) << ply.out;
}

// The acceptance case: 12 simulated views of the bundled mustard bottle,
// merged by turntable, within three times the configured depth noise of the mesh.
TEST(Cli, ScanOfTheBundledSampleMatchesTheMesh) {
  test::TempDir dir;
  const std::string out = (dir / "scan").string();
  const double noise = 0.0005;
  const CmdResult r = run("scan --config " + repo("config/default.yaml") + " -o " + out +
                    " --views 12 --set noise=" + std::to_string(noise) + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_EQ(json_number(r.out, "views"), 12);
  const SessionManifest m = read_manifest(out);
  ASSERT_EQ(m.views.size(), 12u);
  ASSERT_TRUE(m.axis.has_value());
  ASSERT_TRUE(m.views[5].reference_pose.has_value());
  EXPECT_FALSE(m.views[5].colour_image.empty());
  const Cloud merged = read_cloud(out + "/merged.ply");
  EXPECT_GT(merged.size(), 50000u);
  EXPECT_TRUE(merged.has_colours());

  const CmdResult e = run("eval " + out + "/merged.ply " + repo("data/mustard_bottle/textured.obj") +
                    " --samples 100000 --json");
  ASSERT_EQ(e.code, 0) << e.out;
  const double chamfer = json_number(e.out, "chamfer");
  RecordProperty("chamfer_m", std::to_string(chamfer));
  // The reference is textured, so colour is compared too (sim colour noise sigma = 2/255).
  const double e_col = json_number(e.out, "color_error");
  EXPECT_GT(e_col, 0) << e.out;
  EXPECT_LT(e_col, 0.15) << e.out;

  // The rest of today's pipeline: consolidate, reconstruct a coloured mesh, measure it.
  const std::string thin = out + "/thin.ply", mesh = out + "/mesh.ply";
  CmdResult c = run("consolidate " + out + "/merged.ply -o " + thin + " --points 20000 --json");
  ASSERT_EQ(c.code, 0) << c.out;
  EXPECT_EQ(read_cloud(thin).size(), 20000u);
  c = run("reconstruct " + thin + " -o " + mesh + " --resolution 96 --json");
  ASSERT_EQ(c.code, 0) << c.out;
  // DMC reports the cells its feature step left alone where the MPU surface is smooth.
  EXPECT_GE(json_number(c.out, "smooth_cells"), 0) << c.out;
  const Mesh reconstructed = read_mesh(mesh);
  EXPECT_GT(reconstructed.faces.size(), 10000u);
  EXPECT_TRUE(reconstructed.has_colours());
  c = run("eval " + mesh + " " + repo("data/mustard_bottle/textured.obj") + " --samples 100000 --json");
  ASSERT_EQ(c.code, 0) << c.out;
  EXPECT_LT(json_number(c.out, "chamfer"), 0.002) << c.out;
  EXPECT_LT(json_number(c.out, "color_error"), 0.2) << c.out;
  // --no-colour-edges keeps the extracted faces (the label's print splits some by default).
  const std::string plain_mesh = out + "/mesh_plain.ply";
  CmdResult p = run("reconstruct " + thin + " -o " + plain_mesh + " --resolution 96 --no-colour-edges --json");
  ASSERT_EQ(p.code, 0) << p.out;
  EXPECT_EQ(json_number(p.out, "colour_edges_split"), 0) << p.out;
  EXPECT_LT(read_mesh(plain_mesh).faces.size(), reconstructed.faces.size());
  EXPECT_GT(chamfer, 0);
  EXPECT_LT(chamfer, 3 * noise) << e.out;
}

// Issue 32: the Stanford scans are not stored in their scanner frame. With their
// normals turned towards the origin (inside the dragon) 80 % faced inwards: the
// closed mesh got a second sheet around the whole dragon (mesh -> scans over 3 mm),
// hole auto found nothing enclosed, and the kept mesh spanned more (0.78 / p95
// 2.29 mm on this bundled copy). Now: closed 1.47 mm, kept 0.60 / 1.79 mm.
TEST(Cli, DragonRunIsOneSheetNearTheScans) {
  test::TempDir dir;
  std::string files;
  for (int a = 0; a < 360; a += 24) files += " " + repo("data/dragon_stand/dragonStandRight_" + std::to_string(a) + ".ply");
  const std::string session = (dir / "dragon").string();
  CmdResult r = run("import" + files + " --step 24 -o " + session);
  ASSERT_EQ(r.code, 0) << r.out;
  const std::string closed = (dir / "closed").string(), kept = (dir / "kept").string();
  r = run("run " + session + " -o " + closed + " --no-report");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("15 of 15 views are not stored in their scanner frame"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("closing the unseen parts (hole auto"), std::string::npos) << r.out;
  r = run("eval " + closed + "/mesh.ply " + closed + "/merged.ply --json");
  ASSERT_EQ(r.code, 0) << r.out;
  std::smatch m;
  const std::regex a_to_b("\"a_to_b\":\\{\"mean\":([-0-9.eE+]+),\"rms\":[-0-9.eE+]+,\"p95\":([-0-9.eE+]+)");
  ASSERT_TRUE(std::regex_search(r.out, m, a_to_b)) << r.out;
  EXPECT_LT(std::stod(m[1]), 0.002) << r.out;

  // The same consolidated points meshed with and without their scans (issue 32's
  // snap): closer to the scans, no further from them the other way.
  const std::string cons = closed + "/consolidated.ply", merged = closed + "/merged.ply";
  const std::string plain = (dir / "plain.ply").string(), snapped = (dir / "snapped.ply").string();
  r = run("reconstruct " + cons + " -o " + plain + " --hole close --json");
  ASSERT_EQ(r.code, 0) << r.out;
  r = run("reconstruct " + cons + " -o " + snapped + " --hole close --scans " + merged + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_GT(json_number(r.out, "snapped_vertices"), 1000) << r.out;
  const std::regex b_to_a("\"b_to_a\":\\{\"mean\":([-0-9.eE+]+)");
  double to_mesh[2], to_scans[2];
  for (int k = 0; k < 2; ++k) {
    r = run("eval " + (k ? snapped : plain) + " " + merged + " --json");
    ASSERT_EQ(r.code, 0) << r.out;
    ASSERT_TRUE(std::regex_search(r.out, m, b_to_a)) << r.out;
    to_mesh[k] = std::stod(m[1]);
    ASSERT_TRUE(std::regex_search(r.out, m, a_to_b)) << r.out;
    to_scans[k] = std::stod(m[1]);
  }
  std::printf("dragon, scans -> mesh %.5f -> %.5f mm; mesh -> scans %.4f -> %.4f mm\n", to_mesh[0] * 1e3,
              to_mesh[1] * 1e3, to_scans[0] * 1e3, to_scans[1] * 1e3);
  EXPECT_LT(to_mesh[1], 0.99 * to_mesh[0]);
  EXPECT_LT(to_scans[1], 1.02 * to_scans[0]);
  // Scans without normals: a one-line error naming the file.
  Cloud bare = read_cloud(merged);
  bare.normals.clear();
  const std::string bare_file = (dir / "bare.ply").string();
  write_ply(bare_file, bare);
  r = run("reconstruct " + cons + " -o " + (dir / "bare_mesh.ply").string() + " --scans " + bare_file);
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.out.find("bare.ply: the scans have no normals"), std::string::npos) << r.out;

  r = run("run " + session + " -o " + kept + " --no-report --hole keep --quiet");
  ASSERT_EQ(r.code, 0) << r.out;
  r = run("eval " + kept + "/mesh.ply " + kept + "/merged.ply --json");
  ASSERT_EQ(r.code, 0) << r.out;
  ASSERT_TRUE(std::regex_search(r.out, m, a_to_b)) << r.out;
  EXPECT_LT(std::stod(m[1]), 0.0007) << r.out;
  EXPECT_LT(std::stod(m[2]), 0.0021) << r.out;
}

// The dragon's files as a shell glob gives them (text order: _0, _120, _144,
// ..., _24, ...): imported in that order, with a warning naming the first pair
// out of the numbers' order and what --step then does.
TEST(Cli, ImportWarnsOfFilesInAShellGlobsOrder) {
  test::TempDir dir;
  std::vector<std::string> names;
  for (int a = 0; a < 360; a += 24) names.push_back("dragonStandRight_" + std::to_string(a) + ".ply");
  std::sort(names.begin(), names.end());
  std::string files;
  for (const std::string& n : names) files += " " + repo("data/dragon_stand/" + n);
  CmdResult r = run("import" + files + " --step 24 -o " + (dir / "glob").string());
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("warning: the files are not in the order of the numbers in their names "
                       "(dragonStandRight_216.ply before dragonStandRight_24.ply)"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("--step gives their angles in it"), std::string::npos) << r.out;
  EXPECT_DOUBLE_EQ(*read_manifest(dir / "glob").views.at(1).angle_deg, 24.0);  // the order given
}

// Bad views to import: an empty cloud, a file given twice, a copy of another view,
// a --stanford-conf that is not one or names none of the files. Each is one line naming
// the file, before anything is written; a copy is imported with a warning.
TEST(Cli, ImportRefusesEmptyOrRepeatedViewsAndAConfThatIsNotOne) {
  namespace fs = std::filesystem;
  test::TempDir dir;
  const std::string a = repo("data/dragon_stand/dragonStandRight_0.ply");
  const std::string b = repo("data/dragon_stand/dragonStandRight_24.ply");
  const std::string empty = (dir / "empty.ply").string();
  write_ply(empty, Cloud{});
  const std::string session = (dir / "s").string();
  CmdResult r = run("import " + a + " " + empty + " --step 24 -o " + session);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("empty.ply: no points; an empty view cannot be imported"), std::string::npos) << r.out;
  EXPECT_FALSE(fs::exists(session));
  r = run("import " + a + " " + b + " " + a + " --step 24 -o " + session);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("dragonStandRight_0.ply: given twice (views 0 and 2)"), std::string::npos) << r.out;
  EXPECT_FALSE(fs::exists(session));
  const std::string garbage = (dir / "garbage.conf").string();
  std::ofstream(garbage) << "this is not\na conf file\n";
  r = run("import " + a + " " + b + " --step 24 --stanford-conf " + garbage + " -o " + session);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("garbage.conf: no 'bmesh FILE"), std::string::npos) << r.out;
  const std::string other = (dir / "other.conf").string();
  std::ofstream(other) << "bmesh elsewhere.ply 0 0 0 0 0 0 1\n";
  r = run("import " + a + " " + b + " --step 24 --stanford-conf " + other + " -o " + session);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("other.conf: names none of the imported files (its first is elsewhere.ply)"),
            std::string::npos)
      << r.out;
  EXPECT_FALSE(fs::exists(session));
  const std::string copy = (dir / "copy.ply").string();
  fs::copy_file(b, copy);
  r = run("import " + a + " " + b + " " + copy + " --step 24 -o " + session);
  EXPECT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("warning: " + copy + " has the same points as " + b), std::string::npos) << r.out;
  // The dragon's scans are in metres: imported as millimetres, the registration says so.
  const std::string mm = (dir / "mm").string();
  ASSERT_EQ(run("import " + a + " " + b + " --step 24 --units mm -o " + mm).code, 0);
  r = run("register " + mm + " -o " + (dir / "mm.ply").string());
  EXPECT_NE(r.out.find("mm across (median view diagonal) while the session says units: mm: are they in metres?"),
            std::string::npos)
      << r.out;
  r = run("register " + session + " -o " + (dir / "m.ply").string());
  EXPECT_EQ(r.out.find("are they in"), std::string::npos) << r.out;
}

// A view of the session that cannot be read: the axis comes from the others, the
// view is named, and the exit is 3 (a partial result, as register's), not 0.
TEST(Cli, CalibrateTurntableWithAnUnreadableViewExitsThree) {
  namespace fs = std::filesystem;
  test::TempDir dir;
  std::string files;
  for (int a = 0; a < 120; a += 24) files += " " + repo("data/dragon_stand/dragonStandRight_" + std::to_string(a) + ".ply");
  const std::string session = (dir / "s").string();
  CmdResult r = run("import" + files + " --step 24 -o " + session);
  ASSERT_EQ(r.code, 0) << r.out;
  const fs::path view = fs::path(session) / "view_002.ply";
  const std::string bytes = read_file_bytes(view);
  std::ofstream(view, std::ios::binary | std::ios::trunc) << bytes.substr(0, bytes.size() / 2);
  const std::string axis = (dir / "axis.yaml").string();
  r = run("calibrate turntable " + session + " -o " + axis);
  EXPECT_EQ(r.code, 3) << r.out;
  EXPECT_NE(r.out.find("view_002.ply"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("calibrate turntable: the axis is fitted to 4 of 5 views; not registered: views[2] (view_002.ply)"),
            std::string::npos)
      << r.out;
  EXPECT_TRUE(fs::exists(axis));
}

TEST(Cli, DragonImportsAndReplaysLikeALiveScanner) {
  test::TempDir dir;
  std::string files;
  for (int a = 0; a < 360; a += 24) files += " " + repo("data/dragon_stand/dragonStandRight_" + std::to_string(a) + ".ply");
  const std::string session = (dir / "dragon").string();
  CmdResult r = run("import" + files + " --step 24 --stanford-conf " +
              repo("data/dragon_stand/dragonStandRight.conf") + " -o " + session + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_EQ(r.out.find("warning: the files are not in the order"), std::string::npos) << r.out;
  const SessionManifest m = read_manifest(session);
  ASSERT_EQ(m.views.size(), 15u);
  EXPECT_DOUBLE_EQ(*m.views[14].angle_deg, 336.0);
  ASSERT_TRUE(m.views[1].reference_pose.has_value());
  // Stanford's 24-degree pose is a rotation of about 24 degrees about y.
  const Eigen::Matrix3d R = m.views[1].reference_pose->block<3, 3>(0, 0);
  EXPECT_NEAR(std::acos((R.trace() - 1) / 2) * 180 / M_PI, 24.0, 0.5);

  // Registration with the angles but not the axis, measured against Stanford's poses
  // (docs/registration.md): the views held on one rigid turntable reach the issue's
  // rotation targets (0.5 degree, median 0.25); free poses do not.
  const std::string merged = (dir / "merged.ply").string(), poses = (dir / "poses.yaml").string();
  r = run("register " + session + " -o " + merged + " --poses-out " + poses + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_LT(json_number(r.out, "max_rotation_deg"), 0.5) << r.out;
  EXPECT_LT(json_number(r.out, "median_rotation_deg"), 0.25) << r.out;
  EXPECT_NE(r.out.find("\"rigid_turntable\":{\"used\":true"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"runs\":1,\"moved_before_views\":[]"), std::string::npos) << r.out;  // one run: no move
  CmdResult free_poses = run("register " + session + " -o " + merged + " --rigid-turntable off --json");
  ASSERT_EQ(free_poses.code, 0) << free_poses.out;
  EXPECT_NE(free_poses.out.find("\"rigid_turntable\":{\"used\":false"), std::string::npos) << free_poses.out;
  EXPECT_GT(json_number(free_poses.out, "max_rotation_deg"), 0.5) << free_poses.out;
  EXPECT_EQ(run("register " + session + " -o " + merged + " --rigid-turntable sideways").code, 2);
  r = run("register " + session + " -o " + merged + " --poses-out " + poses + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("\"14-0\":{\"converged\":true"), std::string::npos) << r.out;  // loop closure
  EXPECT_GT(read_cloud(merged).size(), 80000u);
  EXPECT_NE(read_file_bytes(poses).find("view_014.ply"), std::string::npos);
  // The turntable axis from the registered views: the dragon turns about the scanner's y.
  const std::string axis = (dir / "axis.yaml").string();
  r = run("calibrate turntable " + session + " -o " + axis + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  std::smatch dm;
  ASSERT_TRUE(std::regex_search(r.out, dm, std::regex("\"direction\":\\[([^,]+),([^,]+),([^\\]]+)\\]")))
      << r.out;
  EXPECT_GT(std::abs(std::stod(dm[2])), 0.999) << r.out;
  EXPECT_LT(json_number(r.out, "rms_tilt_deg"), 0.5) << r.out;
  EXPECT_NE(read_file_bytes(axis).find("direction:"), std::string::npos);

  const std::string replayed = (dir / "replayed").string();
  r = run("replay " + session + " -o " + replayed + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  const SessionManifest rm = read_manifest(replayed);
  ASSERT_EQ(rm.views.size(), 15u);
  for (std::size_t i = 0; i < 15; ++i) {
    EXPECT_EQ(rm.views[i].points, m.views[i].points) << i;
    EXPECT_NEAR(*rm.views[i].angle_deg, *m.views[i].angle_deg, 0.2) << i;
  }

  // A wrong commanded angle (view 7 says 198 instead of 168 degrees) is found,
  // recovered and reported by name; --no-angle-check trusts it instead.
  SessionManifest wrong = m;
  wrong.views[7].angle_deg = *wrong.views[7].angle_deg + 30;
  write_manifest(session, wrong);
  r = run("register " + session + " -o " + merged + " --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("\"7\":{\"registered\":true,\"initial\":\"global_features\""), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"angle_rejected\":true"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("views[7]"), std::string::npos) << r.out;
  EXPECT_LT(json_number(r.out, "max_rotation_deg"), 0.5) << r.out;
  r = run("register " + session + " -o " + merged + " --no-angle-check --no-global --json");
  EXPECT_EQ(r.out.find("\"angle_rejected\":true"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"warnings\":[]"), std::string::npos) << r.out;
  r = run("register " + session + " -o " + merged + " --objective sideways");
  EXPECT_EQ(r.code, 2) << r.out;
}

TEST(Cli, EvalPointsMetrics) {
  test::TempDir dir;
  // Points 0.01 outside a cube's faces: accuracy and edge error are 0.01 exactly.
  const Mesh cube = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const std::string cube_ply = (dir / "cube.ply").string();
  write_ply(cube_ply, cube);
  Cloud shell = sample_mesh(cube, 3000, 3);
  for (std::size_t i = 0; i < shell.size(); ++i) shell.points[i] += 0.01f * shell.normals[i];
  const std::string shell_ply = (dir / "shell.ply").string();
  write_ply(shell_ply, shell);
  CmdResult r = run("eval " + shell_ply + " " + cube_ply + " --samples 1000 --edge-radius 0.2 --json");
  ASSERT_EQ(r.code, 0) << r.out;
  const Cloud read = read_cloud(shell_ply);
  EXPECT_NEAR(json_number(r.out, "accuracy"), 0.01, 1e-6) << r.out;
  EXPECT_NEAR(json_number(r.out, "edge_error"), 0.01, 1e-6) << r.out;
  const EdgeError ee = edge_error(read.points, cube, 0.2);
  EXPECT_GT(ee.count, 300u);
  EXPECT_EQ(json_number(r.out, "edge_points"), double(ee.count)) << r.out;
  EXPECT_EQ(json_number(r.out, "sharp_edges"), 12) << r.out;
  EXPECT_NEAR(json_number(r.out, "uniformity"), surface_uniformity(read.points, cube), 1e-6) << r.out;
  EXPECT_NEAR(json_number(r.out, "uniformity_3d"), uniformity(read.points, 24.0), 1e-6) << r.out;
  // Text output; without --edge-radius the edge error is n/a.
  r = run("eval " + shell_ply + " " + cube_ply + " --samples 1000 --points-metrics");
  ASSERT_EQ(r.code, 0) << r.out;
  std::smatch m;
  ASSERT_TRUE(std::regex_search(r.out, m, std::regex("accuracy \\(mean distance to B\\) ([0-9.e-]+)"))) << r.out;
  EXPECT_NEAR(std::stod(m[1]), 0.01, 1e-5) << r.out;
  EXPECT_NE(r.out.find("edge error: n/a"), std::string::npos) << r.out;
  // The reference must be a mesh.
  r = run("eval " + shell_ply + " " + shell_ply + " --samples 1000 --points-metrics");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("B must be a mesh"), std::string::npos) << r.out;
  // ... with an area: a reference whose faces are all degenerate is named by its own
  // file (it was blamed on A).
  Mesh flat;
  flat.vertices = {Vec3f(-1, -1, -1), Vec3f(0, 0, 0), Vec3f(1, 1, 1)};
  flat.faces.push_back(Face(0, 1, 2));
  const std::string flat_ply = (dir / "flat.ply").string();
  write_ply(flat_ply, flat);
  r = run("eval " + shell_ply + " " + flat_ply + " --samples 1000 --points-metrics");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_EQ(r.out.rfind("station: " + flat_ply + ": B: the reference mesh has zero or non-finite area", 0), 0u)
      << r.out;
  EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << r.out;
  // A sphere has no sharp edge: nothing measured is null, not a perfect 0.
  const Mesh ball = test::icosphere(3);
  const std::string ball_ply = (dir / "ball.ply").string();
  write_ply(ball_ply, ball);
  r = run("eval " + shell_ply + " " + ball_ply + " --samples 1000 --edge-radius 0.2 --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("\"edge_error\":null,\"edge_points\":0"), std::string::npos) << r.out;
  r = run("eval " + shell_ply + " " + cube_ply + " --edge-radius -1");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_EQ(r.out.find("different units"), std::string::npos) << r.out;
  // The same cube in millimetres: the sizes differ 1000x, which eval points out.
  Mesh cube_mm = cube;
  for (Vec3f& v : cube_mm.vertices) v *= 1000.f;
  const std::string cube_mm_ply = (dir / "cube_mm.ply").string();
  write_ply(cube_mm_ply, cube_mm);
  r = run("eval " + shell_ply + " " + cube_mm_ply + " --samples 1000");
  EXPECT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("cube_mm.ply is 990x the size of"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("different units?"), std::string::npos) << r.out;

  // End to end on the fandisk (d_bb 1.45) with 0.3 % noise: edge-WLOP's points keep
  // the sharp edges better.
  const std::string fandisk = repo("tests/data/consolidation/fandisk.off");
  const Mesh mesh = read_mesh(fandisk);
  Cloud in = sample_mesh(mesh, 20000, 5);
  std::mt19937 rng(5);
  std::normal_distribution<float> noise(0, 0.0044f);
  for (Vec3f& p : in.points) p += Vec3f(noise(rng), noise(rng), noise(rng));
  const std::string in_ply = (dir / "fandisk.ply").string();
  write_ply(in_ply, Cloud{in.points, {}, {}});
  double edge[3], accuracy[3];
  for (int m = 0; m < 3; ++m) {
    const std::string out = (dir / ("out" + std::to_string(m) + ".ply")).string();
    r = run("consolidate " + in_ply + " -o " + out + " --points 4000 --radius 0.04 --method " +
            (m == 1 ? "edge-wlop --attraction projection" : "wlop --attraction l1") +
            (m == 2 ? " --repulsion tangential" : m == 0 ? " --repulsion full" : ""));
    ASSERT_EQ(r.code, 0) << r.out;
    // Progress on stderr (a 3 M-point cloud took 38 s without a line).
    EXPECT_NE(r.out.find(m == 1 ? "consolidate: edge-WLOP iterations done in"
                                : "consolidate: WLOP iterations done in"),
              std::string::npos)
        << r.out;
    r = run("eval " + out + " " + fandisk + " --samples 1000 --edge-radius 0.08 --json");
    ASSERT_EQ(r.code, 0) << r.out;
    edge[m] = json_number(r.out, "edge_error");
    accuracy[m] = json_number(r.out, "accuracy");
    EXPECT_GT(json_number(r.out, "edge_points"), 500) << r.out;
  }
  // wlop --repulsion tangential drifts less off the surface than E2 as printed, and the
  // projection (edge-wlop here) lands closer still.
  EXPECT_LT(accuracy[2], accuracy[0]) << "full " << accuracy[0] << ", tangential " << accuracy[2];
  EXPECT_LT(accuracy[1], accuracy[2]) << "tangential " << accuracy[2] << ", projection " << accuracy[1];
  r = run("consolidate " + in_ply + " -o " + (dir / "x.ply").string() + " --repulsion sideways");
  EXPECT_NE(r.code, 0);
  RecordProperty("edge_error_wlop", std::to_string(edge[0]));
  RecordProperty("edge_error_edge_wlop", std::to_string(edge[1]));
  EXPECT_LT(edge[1], 0.75 * edge[0]) << "wlop " << edge[0] << ", edge-wlop " << edge[1];
}

TEST(Cli, BadInputGivesOneLineErrorsNamingTheCulprit) {
  test::TempDir dir;
  CmdResult r = run("eval " + (dir / "missing.ply").string() + " " + repo("data/mustard_bottle/textured.obj"));
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("missing.ply"), std::string::npos) << r.out;

  {
    std::ofstream bad((dir / "bad.ply").string());
    bad << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n1 1\n";
  }
  r = run("eval " + (dir / "bad.ply").string() + " " + (dir / "bad.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("bad.ply"), std::string::npos) << r.out;
  EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << r.out;

  r = run("scan --scanner usb:nothing -o " + (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("usb:nothing"), std::string::npos) << r.out;

  r = run("scan --resume -o " + (dir / "nope").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("nope"), std::string::npos) << r.out;

  r = run("scan --config " + (dir / "none.yaml").string() + " -o " + (dir / "y").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("none.yaml"), std::string::npos) << r.out;

  r = run("scan -o /proc/station-cannot-write --views 1");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("/proc/station-cannot-write"), std::string::npos) << r.out;

  r = run("scan --views 0");
  EXPECT_EQ(r.code, 2);

  // The library's complaints about a cloud name its file at the command line, and an
  // output that cannot be written in its format is refused before the work; neither
  // leaves an output behind.
  const auto write_cloud = [&](const std::string& name, const char* rows) {
    std::ofstream t((dir / name).string());
    t << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
         "end_header\n"
      << rows;
    return (dir / name).string();
  };
  const std::string tiny = write_cloud("tiny.ply", "0 0 0\n1 0 0\n0 1 0\n");
  const std::string same = write_cloud("same.ply", "1 2 3\n1 2 3\n1 2 3\n");
  for (const auto& [cmd, in] : {std::pair<std::string, std::string>{"reconstruct", tiny}, {"fit", tiny},
                                {"consolidate --method edge-wlop", same}}) {
    const std::string out = (dir / "out.ply").string();
    r = run(cmd + " --json " + in + " -o " + out);
    EXPECT_EQ(r.code, 1) << cmd;
    EXPECT_EQ(r.out.rfind("station: " + in + ": ", 0), 0u) << cmd << ": " << r.out;
    EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << cmd << ": " << r.out;
    EXPECT_FALSE(std::filesystem::exists(out)) << cmd;
  }
  // The run names the stage and its input.
  r = run("run --quiet " + same + " -o " + (dir / "run_same").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out.rfind("station: " + same + ": consolidate: ", 0), 0u) << r.out;
  const std::string none = (dir / "none.ply").string();
  {
    std::ofstream t(none);
    t << "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
         "end_header\n";
  }
  for (const std::string& args : {none + " " + tiny, tiny + " " + none}) {
    r = run("eval " + args);
    EXPECT_EQ(r.code, 1) << args;
    EXPECT_EQ(r.out.rfind("station: " + none + ": ", 0), 0u) << r.out;
  }
  for (const std::string cmd : {"consolidate", "reconstruct"}) {
    const std::string out = (dir / "out.xyz").string();
    r = run(cmd + " " + repo("data/mustard_bottle/textured.obj") + " -o " + out);
    EXPECT_EQ(r.code, 1) << cmd;
    EXPECT_NE(r.out.find(out + ": a "), std::string::npos) << cmd << ": " << r.out;
    EXPECT_FALSE(std::filesystem::exists(out)) << cmd;
  }
}

// Issue 26's bad sessions through `station register`: every view the same
// cloud with one of 10 points (exit 3, the tiny view named, the angles said to
// fit nothing, the partial result written), and views that overlap nowhere
// (each moved 1 m further along x: every view named, exit 1, nothing written).
TEST(Cli, RegisterOfIdenticalViewsOrViewsThatOverlapNowhereSaysSo) {
  test::TempDir dir;
  const std::string sess = (dir / "s").string();
  ASSERT_EQ(run("scan -o " + sess + " --views 8 --set width=320 --set height=240").code, 0);
  const SessionManifest m = read_manifest(sess);
  ASSERT_EQ(m.views.size(), 8u);
  const auto copy_session = [&](const std::string& name, const std::function<Cloud(std::size_t)>& make) {
    const fs::path to = dir / name;
    fs::create_directories(to);
    fs::copy_file(fs::path(sess) / "session.yaml", to / "session.yaml");
    for (std::size_t i = 0; i < m.views.size(); ++i) write_ply(to / m.views[i].file, make(i));
    return to.string();
  };
  const Cloud first = read_cloud(fs::path(sess) / m.views[0].file);
  const std::string same = copy_session("same", [&](std::size_t i) {
    Cloud c = first;
    if (i == 5) {
      c.points.resize(10);
      c.normals.resize(10);
      c.colours.resize(10);
    }
    return c;
  });
  CmdResult r = run("register " + same + " -o " + (dir / "same.ply").string());
  EXPECT_EQ(r.code, 3) << r.out;
  EXPECT_NE(r.out.find("view_005.ply"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("did the turntable turn"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("7 of 8 views"), std::string::npos) << r.out;
  EXPECT_TRUE(fs::exists(dir / "same.ply"));

  const std::string apart = copy_session("apart", [&](std::size_t i) {
    Cloud c = read_cloud(fs::path(sess) / m.views[i].file);
    for (Vec3f& p : c.points) p.x() += float(i);
    return c;
  });
  // Views that overlap nowhere: the first alone is the partial result (exit 3), every
  // other view named (issue 26's bad input); before, exit 1 and nothing written.
  r = run("register " + apart + " -o " + (dir / "apart.ply").string());
  EXPECT_EQ(r.code, 3) << r.out;
  for (std::size_t i = 1; i < m.views.size(); ++i)
    EXPECT_NE(r.out.find(m.views[i].file + "): no overlap"), std::string::npos) << m.views[i].file;
  EXPECT_NE(r.out.find("no two views overlap: the result is views[0] (" + m.views[0].file + ") alone"),
            std::string::npos)
      << r.out;
  ASSERT_TRUE(fs::exists(dir / "apart.ply"));
  // (the view's own points, less the outliers the registration removes)
  const std::size_t alone = read_cloud(dir / "apart.ply").size(), view0 = read_cloud(fs::path(apart) / m.views[0].file).size();
  EXPECT_LE(alone, view0);
  EXPECT_GT(alone, view0 * 9 / 10);
}

// Coloured ICP on the simulated bottle (objects matched at a millimetre): the paper's
// lambda, set for scenes matched at centimetres, let the colour noise outweigh the
// geometry; pairs drifted (8 of 12 views, 0.93 deg off). Its colour term is now
// scaled to the final distance. A view without colours is named.
TEST(Cli, ColouredRegistrationOfTheSimulatedBottle) {
  test::TempDir dir;
  const std::string sess = (dir / "s").string();
  ASSERT_EQ(run("scan -o " + sess + " --views 12 --set width=320 --set height=240").code, 0);
  CmdResult r = run("register " + sess + " -o " + (dir / "m.ply").string() + " --objective colored --json");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("\"failed_views\":0,"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("\"reference\":{\"views\":12,"), std::string::npos) << r.out;
  const double rot = json_number(r.out, "max_rotation_deg"), at_object = json_number(r.out, "max_object_translation_m");
  EXPECT_GE(rot, 0) << r.out;  // -1: not in the summary
  EXPECT_LT(rot, 0.2) << r.out;
  EXPECT_GE(at_object, 0) << r.out;
  EXPECT_LT(at_object, 2e-4) << r.out;
  Cloud bare = read_cloud(sess + "/view_005.ply");
  bare.colours.clear();
  write_ply(sess + "/view_005.ply", bare);
  r = run("register " + sess + " -o " + (dir / "m.ply").string() + " --objective colored");
  EXPECT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("the coloured ICP objective needs colours, and 1 view has none (views[5] (view_005.ply))"),
            std::string::npos)
      << r.out;
}

// Values no run can mean are refused by name before any work (a bad-input campaign's
// findings): thousands of threads (fit stalled), a consolidation radius larger than the
// cloud (points thrown off the object; 1e308 hung `run`), an icosphere level with
// trailing characters (read as its first digit), a profile's negative threads (blamed
// on the input file, after registration had run); and the campaign's leftovers below
// (calibrate camera's --config, run's radius named by its key, --up, the working
// volume, the largest --samples and --resolution).
TEST(Cli, OddValuesAreRefusedByName) {
  test::TempDir dir;
  const Mesh ball = test::icosphere(4, 0.05);
  Cloud c = sample_mesh(ball, 3000, 5);
  const std::string in = (dir / "ball.ply").string(), out = (dir / "out.ply").string();
  write_ply(in, c);
  CmdResult r = run("fit " + in + " -o " + out + " --threads 10000");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("--threads"), std::string::npos) << r.out;
  r = run("consolidate " + in + " -o " + out + " --points 600 --radius 10");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("radius 10 is larger than the cloud itself"), std::string::npos) << r.out;
  r = run("fit " + in + " -o " + out + " --template icosphere:1e9");
  EXPECT_EQ(r.code, 2) << r.out;  // a bad option value: usage
  EXPECT_NE(r.out.find("expected icosphere:L with L in 0..7"), std::string::npos) << r.out;
  const std::string profile = (dir / "p.yaml").string();
  { std::ofstream(profile) << "threads: -1\n"; }
  r = run("fit " + in + " -o " + out + " --config " + profile);
  EXPECT_NE(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("threads: must be 0..1024"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find("ball.ply"), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(out));
  // Outputs (the second campaign): a folder that does not exist, a poses file not
  // named .yaml (YAML was written into a .ply), a FIFO at the name (it was replaced
  // by a regular file); register checks them before its work.
  r = run("consolidate " + in + " -o " + (dir / "nope" / "c.ply").string() + " --points 600");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("folder " + (dir / "nope").string() + " does not exist"), std::string::npos) << r.out;
  r = run("register " + (dir / "no_session").string() + " -o " + out + " --poses-out " + (dir / "p.ply").string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("the poses file is written as .yaml or .yml"), std::string::npos) << r.out;
  const std::string fifo = (dir / "pipe.ply").string();
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0666), 0);
  r = run("consolidate " + in + " -o " + fifo + " --points 600");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("not a regular file"), std::string::npos) << r.out;
  EXPECT_TRUE(std::filesystem::is_fifo(std::filesystem::symlink_status(fifo)));
  r = run("register " + (dir / "no_session").string() + " -o " + (dir / "nope" / "m.ply").string());
  EXPECT_EQ(r.code, 1) << r.out;  // the missing folder, not the missing session
  EXPECT_NE(r.out.find("folder " + (dir / "nope").string() + " does not exist"), std::string::npos) << r.out;

  // The campaign's leftovers. `calibrate camera` reads its --config as every command
  // does (it was taken and ignored): a bad or missing profile is named before any image.
  const std::string cam_out = (dir / "cam.yaml").string();
  std::string images;
  for (const char* name : {"a.png", "b.png", "c.png"}) images += " " + (dir / name).string();
  r = run("calibrate camera" + images + " --config " + profile + " -o " + cam_out);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("threads: must be 0..1024"), std::string::npos) << r.out;
  r = run("calibrate camera" + images + " --config " + (dir / "none.yaml").string() + " -o " + cam_out);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("none.yaml"), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(cam_out));
  // Bad option values are usage errors (exit 2; these exited 1, while --square 0 exited 2).
  for (const std::string opt : {"--board abc", "--board 2x2", "--square 1e300"}) {
    r = run("calibrate camera" + images + " " + opt + " -o " + cam_out);
    EXPECT_EQ(r.code, 2) << opt << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: " + opt.substr(0, opt.find(' ')) + " ", 0), 0u) << opt << ": " << r.out;
  }
  // `run` refuses a radius no cloud can have with the profile, before any work (it
  // registered the session first); one larger than the cloud, found so only once the
  // cloud is there (after the merge of a session), names its key, not the cloud.
  const std::string run_dir = (dir / "run").string();
  r = run("run --quiet " + in + " -o " + run_dir + " --set consolidate.radius=1e308");
  EXPECT_EQ(r.code, 2) << r.out;  // a bad option value: usage (README)
  EXPECT_EQ(r.out.rfind("station: --set consolidate.radius=1e308: ", 0), 0u) << r.out;
  EXPECT_FALSE(std::filesystem::exists(run_dir));
  r = run("run --quiet " + in + " -o " + run_dir + " --set consolidate.radius=10");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_EQ(r.out.rfind("station: consolidate.radius 10 is larger than the cloud itself", 0), 0u) << r.out;
  EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << r.out;
  EXPECT_FALSE(std::filesystem::exists(run_dir));
  // --up is checked as the command line is parsed (1e308,0,0 failed late, in the
  // table plane's clip; nan,0,1 and 1e-200,0,0 only after the profile was read).
  const std::string mesh_out = (dir / "mesh.ply").string();
  for (const std::string up : {"1e308,0,0", "1e-200,0,0", "nan,0,1"}) {
    r = run("reconstruct " + in + " -o " + mesh_out + " --hole close --up " + up);
    EXPECT_EQ(r.code, 2) << up << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: --up: expected a direction x,y,z", 0), 0u) << up << ": " << r.out;
    EXPECT_FALSE(std::filesystem::exists(mesh_out)) << up;
  }
  // A working volume no bench has is refused by its key before a session is started
  // (a negative radius cropped as its absolute value).
  const std::string sess = (dir / "s").string();
  for (const std::string kv :
       {"capture.volume.radius=-1", "capture.volume.max_height=0", "capture.volume.table_clearance=0.5"}) {
    r = run("scan -o " + sess + " --views 1 --set width=160 --set height=120 --set " + kv);
    EXPECT_EQ(r.code, 2) << kv << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: --set " + kv + ": ", 0), 0u) << kv << ": " << r.out;
    EXPECT_FALSE(std::filesystem::exists(sess)) << kv;
  }
  // The largest --samples and --resolution fit in a few GB (100 M samples and 4096
  // cells in one piece ran out of memory, naming neither option); refused before the
  // inputs are read.
  r = run("eval " + in + " " + in + " --samples 20000001");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_EQ(r.out, "station: --samples: must be a whole number in 1..20000000 (got 20000001)\n");
  r = run("reconstruct " + (dir / "missing.ply").string() + " -o " + mesh_out + " --resolution 4096");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_EQ(r.out.rfind("station: --resolution 4096: must be auto or 8..2048 in one piece", 0), 0u) << r.out;
}

// The same session in millimetres (`units: mm`, every coordinate x 1000) registers as
// well, coloured ICP included, and says the same millimetres and metres: the profile's
// absolute lengths are taken into the session's units and the figures out of them.
TEST(Cli, RegistrationOfASessionInMillimetres) {
  test::TempDir dir;
  const std::string sess = (dir / "s").string(), mm = (dir / "mm").string();
  ASSERT_EQ(run("scan -o " + sess + " --views 12 --set width=320 --set height=240").code, 0);
  std::filesystem::create_directories(mm);
  SessionManifest m = read_manifest(sess);
  for (ViewRecord& v : m.views) {
    Cloud c = read_cloud(sess + "/" + v.file);
    for (Vec3f& p : c.points) p *= 1000.0f;
    write_ply(mm + "/" + v.file, c);
    if (!v.colour_image.empty()) std::filesystem::copy_file(sess + "/" + v.colour_image, mm + "/" + v.colour_image);
    for (std::optional<Eigen::Matrix4d>* pose : {&v.initial_pose, &v.reference_pose})
      if (*pose) (**pose).block<3, 1>(0, 3) *= 1000.0;
  }
  if (m.axis) m.axis->point *= 1000.0;
  m.units = "mm";
  write_manifest(mm, m);
  for (const std::string objective : {"point-to-plane", "colored"}) {
    const CmdResult a = run("register " + sess + " -o " + (dir / "a.ply").string() + " --json --objective " + objective);
    const CmdResult b = run("register " + mm + " -o " + (dir / "b.ply").string() + " --json --objective " + objective);
    ASSERT_EQ(a.code, 0) << a.out;
    ASSERT_EQ(b.code, 0) << b.out;
    EXPECT_NE(b.out.find("\"failed_views\":0,"), std::string::npos) << b.out;
    // The same figures in metres. The poses agree to float rounding's chaos: the
    // point-to-plane runs within 10 %; the coloured ones land tens of um from the truth
    // either way (both well inside the bound below).
    for (const std::string key : {"pair_rmse_m", "max_object_translation_m"}) {
      if (objective == "colored" && key == "max_object_translation_m") continue;
      const double va = json_number(a.out, key), vb = json_number(b.out, key);
      EXPECT_GT(va, 0) << key << " " << a.out;
      EXPECT_NEAR(vb, va, 0.1 * va + 2e-6) << objective << " " << key;
    }
    EXPECT_NE(b.out.find("\"reference\":{\"views\":12,"), std::string::npos) << b.out;
    EXPECT_GE(json_number(b.out, "max_rotation_deg"), 0) << b.out;  // -1: not in the summary
    EXPECT_LT(json_number(b.out, "max_rotation_deg"), 0.2) << b.out;
    EXPECT_GE(json_number(b.out, "max_object_translation_m"), 0) << b.out;
    EXPECT_LT(json_number(b.out, "max_object_translation_m"), 2e-4) << b.out;
  }
  // The table and the pair residual in millimetres, not thousands of them.
  const CmdResult t = run("register " + mm + " -o " + (dir / "b.ply").string());
  ASSERT_EQ(t.code, 0) << t.out;
  std::smatch at;
  ASSERT_TRUE(std::regex_search(t.out, at, std::regex("pair residual \\(RMS point-to-plane over \\d+ refined pairs\\): ([0-9.]+) mm")))
      << t.out;
  EXPECT_GT(std::stod(at[1]), 0.01) << t.out;
  EXPECT_LT(std::stod(at[1]), 2.0) << t.out;
}

// A view that cannot be read fails alone: `run` makes the mesh from the others and
// exits 3 (a partial result, as `register` does), also when the register stage is reused.
TEST(Cli, RunWithABrokenViewIsAPartialResult) {
  test::TempDir dir;
  const std::string sess = (dir / "s").string(), out = (dir / "run").string();
  ASSERT_EQ(run("scan -o " + sess + " --views 12 --set width=320 --set height=240").code, 0);
  {
    std::ofstream bad(sess + "/view_002.ply", std::ios::trunc);
    bad << "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
           "end_header\nnan nan nan\n";
  }
  const std::string small = " --set consolidate.points=3000 --set reconstruct.resolution=48";
  CmdResult r = run("run " + sess + " -o " + out + small);
  EXPECT_EQ(r.code, 3) << r.out;
  EXPECT_NE(r.out.find("view_002.ply"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("1 of 12 views failed registration"), std::string::npos) << r.out;
  EXPECT_TRUE(std::filesystem::exists(out + "/mesh.ply"));
  r = run("run " + sess + " -o " + out + small + " --resume --json");
  EXPECT_EQ(r.code, 3) << r.out;
  // No output replaces a recording: a view file, a colour image or the manifest.
  const std::string view1 = read_file_bytes(sess + "/view_001.ply");
  for (const std::string& args : {"register " + sess + " -o " + sess + "/view_001.ply",
                                  "consolidate " + sess + "/view_003.ply -o " + sess + "/./view_001.ply",
                                  "register " + sess + " -o " + (dir / "m.ply").string() + " --poses-out " + sess +
                                      "/session.yaml",
                                  "reconstruct " + sess + "/view_003.ply -o " + sess + "/view_001.png"}) {
    r = run(args);
    EXPECT_EQ(r.code, 1) << args;
    EXPECT_NE(r.out.find("part of the session recorded in"), std::string::npos) << args << ": " << r.out;
  }
  EXPECT_EQ(read_file_bytes(sess + "/view_001.ply"), view1);
  EXPECT_EQ(read_manifest(sess).views.size(), 12u);
  // Replaying the recording stops at the broken view; the message says what is kept.
  const std::string again = (dir / "again").string();
  r = run("replay " + sess + " -o " + again);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("view_002.ply"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("the 2 views recorded before it are kept in " + again), std::string::npos) << r.out;
  // and how to go on (the replayed session names its scanner, so scan --resume continues it).
  EXPECT_NE(r.out.find("continue with: station scan --resume -o " + again), std::string::npos) << r.out;
  EXPECT_EQ(read_manifest(again).views.size(), 2u);
}

TEST(Cli, ExistingSessionIsNeverOverwritten) {
  test::TempDir dir;
  const std::string out = (dir / "s").string();
  const std::string small = " --views 2 --set width=80 --set height=60";
  ASSERT_EQ(run("scan -o " + out + small).code, 0);
  const std::string manifest = read_file_bytes(out + "/session.yaml");
  const CmdResult again = run("scan -o " + out + small);
  EXPECT_EQ(again.code, 1);
  EXPECT_NE(again.out.find("--resume"), std::string::npos) << again.out;
  EXPECT_EQ(read_file_bytes(out + "/session.yaml"), manifest);
  // Resuming a complete session records nothing new.
  const CmdResult resumed = run("scan --resume -o " + out + " --json");
  EXPECT_EQ(resumed.code, 0) << resumed.out;
  EXPECT_EQ(json_number(resumed.out, "recorded"), 0);
}

// A folder that holds the user's files and no session is not scanned or replayed into
// (replay replaced its merged.ply and view_001.png, exit 0); and a replay whose first
// view fails leaves no stub session behind ("nothing was recorded", but session.yaml
// with no views stayed and blocked the next try).
TEST(Cli, ASessionGoesIntoANewOrEmptyFolderAndAFailedStartLeavesNone) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const std::string src = (dir / "s").string(), user = (dir / "user").string();
  ASSERT_EQ(run("scan -o " + src + " --views 2 --set width=80 --set height=60").code, 0);
  fs::create_directory(user);
  { std::ofstream(user + "/merged.ply") << "the user's"; }
  for (const std::string& cmd : {"replay " + src + " -o " + user, "scan -o " + user + " --views 2"}) {
    const CmdResult r = run(cmd);
    EXPECT_EQ(r.code, 1) << cmd << ": " << r.out;
    EXPECT_NE(r.out.find(user + ": holds other files and no session"), std::string::npos) << r.out;
    EXPECT_EQ(read_file_bytes(user + "/merged.ply"), "the user's");
    EXPECT_FALSE(fs::exists(user + "/session.yaml"));
  }
  // Nor does an import replace a user's file that has a view's name (not an input).
  { std::ofstream(user + "/view_000.ply") << "the user's view"; }
  const CmdResult imp = run("import " + src + "/view_001.ply -o " + user);
  EXPECT_EQ(imp.code, 1) << imp.out;
  EXPECT_NE(imp.out.find(user + "/view_000.ply: exists, and an import never replaces a file"), std::string::npos)
      << imp.out;
  EXPECT_EQ(read_file_bytes(user + "/view_000.ply"), "the user's view");
  EXPECT_FALSE(fs::exists(user + "/session.yaml"));
  // An empty folder is fine.
  fs::create_directory(dir / "empty");
  EXPECT_EQ(run("replay " + src + " -o " + (dir / "empty").string()).code, 0);
  // The first view cannot be replayed (its file cut short): nothing is left.
  const std::string view = src + "/view_000.ply";
  const std::string whole = read_file_bytes(view);
  { std::ofstream(view, std::ios::binary) << whole.substr(0, whole.size() / 2); }
  const std::string again = (dir / "again").string();
  const CmdResult r = run("replay " + src + " -o " + again);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("nothing was recorded"), std::string::npos) << r.out;
  EXPECT_FALSE(fs::exists(again)) << r.out;
}

// A replayed view's colour image is kept when it is not the size of the session's
// intrinsics (it was dropped without a word: the replayed session had no colour).
TEST(Cli, AReplayKeepsColourImagesOfAnotherSize) {
  test::TempDir dir;
  const std::string src = (dir / "s").string(), out = (dir / "r").string();
  ASSERT_EQ(run("scan -o " + src + " --views 2 --set width=80 --set height=60").code, 0);
  SessionManifest m = read_manifest(src);
  ASSERT_TRUE(m.intrinsics);
  ASSERT_FALSE(m.views[0].colour_image.empty());
  m.intrinsics->width *= 2;  // the depth camera's size, say; the images stay 80 x 60
  m.intrinsics->height *= 2;
  write_manifest(src, m);
  const CmdResult r = run("replay " + src + " -o " + out);
  ASSERT_EQ(r.code, 0) << r.out;
  const SessionManifest rm = read_manifest(out);
  ASSERT_EQ(rm.views.size(), 2u);
  for (const ViewRecord& v : rm.views) {
    ASSERT_FALSE(v.colour_image.empty()) << r.out;
    const Texture image = load_texture(out + "/" + v.colour_image);
    EXPECT_EQ(image.width, 80);
    EXPECT_EQ(image.height, 60);
  }
}

// A scan whose views come out empty (the object is not where the scanner looks):
// every view empty is an error that keeps no session (12 empty views and their
// images were kept, "no points in any view", and a later run picked them up); some
// empty views are a warning naming them (10 of 12 empty exited 0 without a word).
TEST(Cli, AScanOfNothingSaysSoAndKeepsNoSession) {
  test::TempDir dir;
  const std::string tiny = (dir / "tiny").string();
  // The bottle at a thousandth of its size: below the table clearance.
  CmdResult r = run("scan -o " + tiny + " --views 3 --set width=80 --set height=60 --set scale=0.001");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(tiny + ": no points in any of the 3 views: is the object inside the working volume"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("; nothing was kept"), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(tiny)) << r.out;
  // The bottle four times too large, the camera inside it from two sides: those two
  // views are empty, said (exit 0: the others hold the object).
  const std::string huge = (dir / "huge").string();
  r = run("scan -o " + huge + " --views 4 --set width=80 --set height=60 --set scale=4");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("warning: 2 of 4 views have no points (views 1, 2): is the object inside the working volume"),
            std::string::npos)
      << r.out;
  const SessionManifest m = read_manifest(huge);
  ASSERT_EQ(m.views.size(), 4u);
  EXPECT_EQ(m.views[1].points, 0u);
  EXPECT_GT(m.views[0].points, 0u);
}

// A single range image without normals (an organised PCD, as PCL writes a Kinect
// frame): its surface faces the camera. The surface stage's own orientation turned
// the campaign's RGB-D clouds away from it (16-27 % of the faces faced the sensor).
TEST(Cli, ARangeImageIsReconstructedFacingItsSensor) {
  test::TempDir dir;
  const int w = 40, h = 30;
  std::string pcd = "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH " +
                    std::to_string(w) + "\nHEIGHT " + std::to_string(h) +
                    "\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS " + std::to_string(w * h) + "\nDATA ascii\n";
  // A wavy wall a metre in front of the camera (+z), 0.4 x 0.3 m.
  for (int r = 0; r < h; ++r)
    for (int c = 0; c < w; ++c) {
      const double x = 0.01 * (c - w / 2), y = 0.01 * (r - h / 2);
      const double z = 1 + 0.02 * std::sin(15 * x) * std::cos(12 * y);
      char line[96];
      std::snprintf(line, sizeof line, "%.6f %.6f %.6f\n", x, y, z);
      pcd += line;
    }
  const std::string in = (dir / "frame.pcd").string(), out = (dir / "mesh.ply").string();
  { std::ofstream(in) << pcd; }
  const CmdResult r = run("reconstruct " + in + " -o " + out + " --threads 2");
  ASSERT_EQ(r.code, 0) << r.out;
  EXPECT_NE(r.out.find("no normals; estimated (PCA) facing the sensor at (0, 0, 0): one range image"),
            std::string::npos)
      << r.out;
  const Mesh m = read_mesh(out);
  ASSERT_GT(m.faces.size(), 100u);
  std::size_t facing = 0;
  for (const Face& f : m.faces) {
    const Vec3f a = m.vertices[std::size_t(f[0])], b = m.vertices[std::size_t(f[1])], c = m.vertices[std::size_t(f[2])];
    facing += (b - a).cross(c - a).dot(-a) > 0;
  }
  EXPECT_GT(double(facing), 0.95 * double(m.faces.size())) << facing << " of " << m.faces.size();
  // Unorganised (HEIGHT 1): may be a merge of views, so nothing is assumed.
  std::string flat = pcd;
  flat.replace(flat.find("WIDTH 40\nHEIGHT 30"), 18, "WIDTH 1200\nHEIGHT 1");
  { std::ofstream(dir / "merged.pcd") << flat; }
  const CmdResult u = run("reconstruct " + (dir / "merged.pcd").string() + " -o " + out + " --threads 2");
  ASSERT_EQ(u.code, 0) << u.out;
  EXPECT_EQ(u.out.find("facing the sensor"), std::string::npos) << u.out;
}

// Inputs that are no files to read, and outputs named for another kind, refused by
// name before any work (a folder as --config was an "internal error", a folder as
// --landmarks was read as none, a landmark at 1e30 bent the fit, calibrate wrote YAML
// into a .ply, parameterise found --mapped m.txt after the fit).
TEST(Cli, OddInputsAndOutputKindsAreRefusedByName) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const std::string cloud = (dir / "cloud.ply").string();
  write_ply(cloud, test::fibonacci_sphere(2000, 0.05));
  const std::string mesh = (dir / "mesh.ply").string();
  write_ply(mesh, test::icosphere(2, 0.05));
  fs::create_directory(dir / "folder");
  const std::string folder = (dir / "folder").string();
  { std::ofstream(dir / "far.txt") << "0 1e30 0 0\n"; }
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"consolidate " + cloud + " -o " + (dir / "c.ply").string() + " --config " + folder,
       folder + ": cannot read: Is a directory"},
      {"consolidate /dev/zero -o " + (dir / "c.ply").string(), "/dev/zero: cannot read: not a regular file"},
      {"fit " + cloud + " -o " + (dir / "f.ply").string() + " --template icosphere:2 --landmarks " + folder,
       folder + ": cannot read: Is a directory"},
      {"fit " + cloud + " -o " + (dir / "f.ply").string() + " --template icosphere:2 --landmarks " +
           (dir / "far.txt").string(),
       (dir / "far.txt").string() + ":1: negative vertex index, or a coordinate not finite or beyond +-1e9"},
      {"parameterise " + mesh + " -o " + (dir / "u.obj").string() + " --mapped " + (dir / "m.txt").string(),
       (dir / "m.txt").string() + ": a mesh is written as .ply or .obj"},
      {"calibrate turntable " + folder + " -o " + (dir / "axis.ply").string(),
       (dir / "axis.ply").string() + ": a profile fragment is written as .yaml or .yml"},
  };
  for (const auto& [cmd, line] : cases) {
    const CmdResult r = run(cmd);
    EXPECT_EQ(r.code, 1) << cmd << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: " + line, 0), 0u) << cmd << ": " << r.out;
    EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << cmd << ": " << r.out;
  }
  for (const char* f : {"c.ply", "f.ply", "u.obj", "axis.ply"}) EXPECT_FALSE(fs::exists(dir / f)) << f;
  // A cloud under a micrometre across: wrong units (a sphere 1e-12 across was fitted
  // with 1,010 flipped faces and reconstructed open, exit 0).
  const std::string tiny = (dir / "tiny.ply").string();
  write_ply(tiny, test::fibonacci_sphere(2000, 1e-9));
  for (const std::string& cmd : {"consolidate " + tiny + " -o " + (dir / "c.ply").string(),
                                 "reconstruct " + tiny + " -o " + (dir / "m.ply").string(),
                                 "fit " + tiny + " -o " + (dir / "f.ply").string() + " --template icosphere:2"}) {
    const CmdResult r = run(cmd);
    EXPECT_EQ(r.code, 1) << cmd << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: " + tiny + ": the cloud spans only ", 0), 0u) << cmd << ": " << r.out;
  }
}

// An output named like one of the command's inputs is refused before the work, naming
// the file, and the input is left as it was (it used to be replaced, exit 0).
TEST(Cli, OutputThatIsAnInputIsRefused) {
  test::TempDir dir;
  const std::string a = (dir / "a.ply").string(), b = (dir / "b.ply").string();
  write_ply(a, test::fibonacci_sphere(400, 0.05));
  write_ply(b, test::fibonacci_sphere(300, 0.05));
  const std::string a_bytes = read_file_bytes(a), b_bytes = read_file_bytes(b);
  const auto refused = [&](const std::string& args, const std::string& named) {
    const CmdResult r = run(args);
    EXPECT_EQ(r.code, 1) << args << ": " << r.out;
    EXPECT_EQ(r.out, "station: " + named + " is also an input; choose another output\n") << args;
  };
  refused("consolidate " + a + " -o " + a, a);
  refused("consolidate " + a + " -o " + (dir / "." / "a.ply").string(), (dir / "." / "a.ply").string());
  refused("reconstruct " + b + " -o " + b, b);
  refused("reconstruct " + a + " --scans " + b + " -o " + b, b);
  refused("fit " + a + " -o " + a, a);
  EXPECT_TRUE(read_file_bytes(a) == a_bytes) << "replaced: " << a;
  EXPECT_TRUE(read_file_bytes(b) == b_bytes) << "replaced: " << b;
  // A run on a cloud in its own run folder, that the run writes (mesh.ply).
  const std::string g = (dir / "g").string();
  std::filesystem::create_directory(g);
  write_ply(g + "/mesh.ply", test::fibonacci_sphere(400, 0.05));
  { std::ofstream(g + "/run.yaml") << "version: 1\ninput: x\nstages: []\n"; }
  const std::string mesh_bytes = read_file_bytes(g + "/mesh.ply");
  CmdResult r = run("run --quiet " + g + "/mesh.ply -o " + g + " --resume --no-report");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_EQ(r.out, "station: " + g + "/mesh.ply is also an input; choose another output folder\n");
  EXPECT_TRUE(read_file_bytes(g + "/mesh.ply") == mesh_bytes) << "replaced: " << g + "/mesh.ply";
  // A file the run does not write is a legitimate input in its folder: a cloud given as
  // input is not registered, so the folder's merged.ply stays (a review found it refused).
  write_ply(g + "/merged.ply", test::fibonacci_sphere(400, 0.05));
  const std::string merged_bytes = read_file_bytes(g + "/merged.ply");
  r = run("run --quiet " + g + "/merged.ply -o " + g + " --resume --no-report");
  EXPECT_EQ(r.out.find("is also an input"), std::string::npos) << r.out;
  EXPECT_TRUE(read_file_bytes(g + "/merged.ply") == merged_bytes) << "replaced: " << g + "/merged.ply";
  // An import into the folder of the file it imports (view_000.ply).
  const std::string d = (dir / "d").string();
  std::filesystem::create_directory(d);
  write_ply(d + "/view_000.ply", test::fibonacci_sphere(400, 0.05));
  const std::string view_bytes = read_file_bytes(d + "/view_000.ply");
  r = run("import " + d + "/view_000.ply --every 2 -o " + d);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("is also an input"), std::string::npos) << r.out;
  EXPECT_TRUE(read_file_bytes(d + "/view_000.ply") == view_bytes) << "replaced: " << d + "/view_000.ply";
  EXPECT_FALSE(std::filesystem::exists(d + "/session.yaml"));
}

// Points on one line outline no surface: the cleanup after the extraction leaves no
// face, and that is an error naming the file with no mesh written (it used to write a
// 0-vertex mesh and exit 0), for `reconstruct` and for `run`'s surface stage.
TEST(Cli, EmptyReconstructedSurfaceIsAnError) {
  test::TempDir dir;
  Cloud line;
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  for (int i = 0; i < 3000; ++i) line.points.emplace_back(u(rng), 0.f, 0.f);
  const std::string in = (dir / "line.ply").string(), out = (dir / "line_mesh.ply").string();
  write_ply(in, line, PlyFormat::kAscii);
  CmdResult r = run("reconstruct --json " + in + " -o " + out);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_EQ(r.out, "station: " + in + ": the reconstructed surface is empty\n");
  EXPECT_FALSE(std::filesystem::exists(out));
  // In blocks alike (blocks need oriented normals): the blocks' own check, no mesh left.
  line.normals.assign(line.points.size(), Vec3f::UnitZ());
  const std::string oriented = (dir / "line_n.ply").string();
  write_ply(oriented, line, PlyFormat::kAscii);
  r = run("reconstruct " + oriented + " -o " + out + " --blocks 2");
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find(oriented + ": the reconstructed surface is empty"), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(out));
  const std::string run_dir = (dir / "run").string();
  r = run("run --quiet --no-report " + in + " -o " + run_dir);
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("surface: the reconstructed surface is empty"), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(run_dir + "/mesh.ply"));
}

// A failed run or import removes what it created and left empty (its output folder),
// and an import that fails part way leaves no stub session.yaml that would block a
// retry ("already holds a session"); folders that existed before are kept.
TEST(Cli, FailedRunOrImportLeavesNothingBehind) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const std::string bad = (dir / "bad").string();
  fs::create_directory(bad);
  { std::ofstream(bad + "/session.yaml") << "version: 1\nviews: [\n"; }
  CmdResult r = run("run --quiet " + bad + " -o " + (dir / "new" / "run").string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_FALSE(fs::exists(dir / "new")) << r.out;
  fs::create_directory(dir / "kept");
  r = run("run --quiet " + bad + " -o " + (dir / "kept").string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_TRUE(fs::is_directory(dir / "kept"));
  // A batch keeps its table, not a folder per failed session.
  { std::ofstream(dir / "list.txt") << "bad\n"; }
  r = run("run --quiet --batch " + (dir / "list.txt").string() + " -o " + (dir / "batch").string());
  EXPECT_EQ(r.code, 3) << r.out;
  EXPECT_TRUE(fs::exists(dir / "batch" / "batch.tsv"));
  EXPECT_FALSE(fs::exists(dir / "batch" / "bad"));

  const std::string cloud = (dir / "cloud.ply").string();
  write_ply(cloud, test::fibonacci_sphere(200, 0.05));
  r = run("import " + cloud + " --step nan -o " + (dir / "imp").string());
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("--step"), std::string::npos) << r.out;
  EXPECT_FALSE(fs::exists(dir / "imp"));
  // The view file cannot be written (a folder holds its name): no stub manifest.
  fs::create_directories(dir / "imp2" / "view_000.ply");
  r = run("import " + cloud + " -o " + (dir / "imp2").string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_FALSE(fs::exists(dir / "imp2" / "session.yaml")) << r.out;
  EXPECT_TRUE(fs::is_directory(dir / "imp2" / "view_000.ply"));
  fs::remove(dir / "imp2" / "view_000.ply");
  r = run("import " + cloud + " -o " + (dir / "imp2").string());
  EXPECT_EQ(r.code, 0) << r.out;
  EXPECT_EQ(read_manifest((dir / "imp2").string()).views.size(), 1u);
}

// An output that cannot be written (its folder missing, a device) is found before
// the work, as `register` does: one line, no progress of the work before it (the
// fit, the consolidation, the surface ran first and failed at the write).
TEST(Cli, AnUnwritableOutputIsFoundBeforeTheWork) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const std::string cloud = (dir / "cloud.ply").string();
  write_ply(cloud, test::fibonacci_sphere(3000, 0.05));
  const std::string mesh = (dir / "mesh.ply").string();
  write_ply(mesh, test::icosphere(3, 0.05));
  const std::string gone = (dir / "no_such_folder").string();
  for (const std::string& cmd :
       {"consolidate " + cloud + " -o " + gone + "/c.ply", "reconstruct " + cloud + " -o " + gone + "/m.ply",
        "fit " + cloud + " -o " + gone + "/f.ply --template icosphere:3",
        "parameterise " + mesh + " -o " + gone + "/u.obj", "reconstruct " + cloud + " -o " + cloud + "/m.ply",
        "parameterise " + mesh + " -o " + (dir / "u.obj").string() + " --mapped " + gone + "/m.ply"}) {
    const CmdResult r = run(cmd);
    EXPECT_EQ(r.code, 1) << cmd << ": " << r.out;
    EXPECT_EQ(r.out.rfind("station: ", 0), 0u) << cmd << ": " << r.out;
    EXPECT_NE(r.out.find("cannot write"), std::string::npos) << cmd << ": " << r.out;
    EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << cmd << ": " << r.out;
  }
  EXPECT_FALSE(fs::exists(gone));
  EXPECT_FALSE(fs::exists(dir / "u.obj"));
}

// Ctrl-C during a long command: one line, exit 130, and nothing of the output
// (before: killed silently by the default action, a temporary left when it came
// during the write; the temporary's removal itself is AtomicFile's test).
TEST(Cli, AnInterruptedCommandSaysSoAndLeavesNothing) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const fs::path view = dir / "view.ply";
  fs::copy_file(repo("data/dragon_stand/dragonStandRight_0.ply"), view);
  // About 7 s of work on one thread here: interrupted after 1 s.
  const CmdResult r = test::run_command("timeout --preserve-status -s INT 1 " + std::string(STATION_BINARY) +
                                        " reconstruct " + view.string() + " -o " +
                                        (dir / "mesh.ply").string() + " --resolution 1024 --threads 1");
  EXPECT_EQ(r.code, 130) << r.out;
  EXPECT_NE(r.out.find("station: interrupted"), std::string::npos) << r.out;
  std::vector<std::string> left;
  for (const auto& e : fs::directory_iterator(dir.path())) left.push_back(e.path().filename().string());
  EXPECT_EQ(left, std::vector<std::string>{"view.ply"});
}

// When one of `register`'s outputs cannot be written, the other one it created goes
// again (it used to stay, with exit 1).
TEST(Cli, RegisterWritesBothOutputsOrNeither) {
  test::TempDir dir;
  const std::string sess = (dir / "s").string();
  ASSERT_EQ(run("scan -o " + sess + " --views 8 --set width=160 --set height=120").code, 0);
  const std::string merged = (dir / "r.ply").string();
  CmdResult r = run("register " + sess + " -o " + merged + " --poses-out " + (dir / "none" / "p.yaml").string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find((dir / "none").string()), std::string::npos) << r.out;
  EXPECT_FALSE(std::filesystem::exists(merged));
  r = run("register " + sess + " -o " + merged + " --poses-out " + (dir / "p.yaml").string());
  EXPECT_TRUE(r.code == 0 || r.code == 3) << r.out;  // (3: a partial result, written all the same)
  EXPECT_TRUE(std::filesystem::exists(merged));
  EXPECT_TRUE(std::filesystem::exists(dir / "p.yaml"));
}

// Command-line parse errors are one plain line (no "Run with --help" second line, no
// 300-digit range, no "A subcommand is required" for a misspelt command), exit 2; and
// a seed is a whole number, 0 or more, for consolidate as for eval.
TEST(Cli, ParseErrorsAreOnePlainLine) {
  test::TempDir dir;
  const std::string cloud = (dir / "c.ply").string();
  write_ply(cloud, test::fibonacci_sphere(200, 0.05));
  const std::string out = (dir / "o.ply").string();
  const std::pair<std::string, std::string> cases[] = {
      {"run " + cloud + " -o " + (dir / "r").string() + " --threads -1",
       "station: --threads: must be a whole number in 0..1024 (got -1)"},
      {"run " + cloud + " -o " + (dir / "r").string() + " --threads abc",
       "station: --threads: must be a whole number in 0..1024 (got abc)"},
      {"bogus", "station: unknown command 'bogus' (station --help lists them)"},
      {"", "station: give a command (station --help lists them)"},
      {"consolidate " + cloud + " -o " + out + " --bogus",
       "station: consolidate: unknown option or extra argument: --bogus (station consolidate --help lists them)"},
      {"consolidate -o " + out, "station: consolidate: input is missing (station consolidate --help)"},
      {"eval " + cloud + " " + cloud + " --seed -1", "station: --seed: must be a whole number, 0 or more (got -1)"},
      {"run " + cloud + " -o " + (dir / "r").string() + " --threads 3000000000",
       "station: --threads: must be a whole number in 0..1024 (got 3000000000)"},
      {"consolidate " + cloud + " -o " + out + " --seed -1", "station: --seed -1: must be a whole number, 0 or more"},
      {"import " + cloud + " -o " + (dir / "i").string() + " --step nan",
       "station: --step: must be a finite number (got nan)"},
  };
  for (const auto& [args, line] : cases) {
    const CmdResult r = run(args);
    EXPECT_EQ(r.code, 2) << args << ": " << r.out;
    EXPECT_EQ(r.out, line + "\n") << args;
  }
  EXPECT_FALSE(std::filesystem::exists(out));
  EXPECT_EQ(run("consolidate --help").code, 0);
}

// Messages that misled: each now names the file or folder and says what is wrong with it
// in the user's terms (not "cannot map: No such device", not an internal function).
TEST(Cli, MessagesNameTheCulpritInPlainWords) {
  test::TempDir dir;
  namespace fs = std::filesystem;
  const auto first_line = [](const CmdResult& r) { return r.out.substr(0, r.out.find('\n')); };
  // A directory given as the cloud (consolidate streams it).
  fs::create_directory(dir / "adir.ply");
  CmdResult r = run("consolidate " + (dir / "adir.ply").string() + " -o " + (dir / "c.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out, "station: " + (dir / "adir.ply").string() + ": cannot read: Is a directory\n");
  // A session whose manifest lists no views: the session named.
  const std::string empty = (dir / "empty").string();
  fs::create_directory(empty);
  {
    std::ofstream(empty + "/session.yaml") << "format: station-session\nversion: 1\nunits: m\nviews: []\n";
  }
  r = run("register " + empty + " -o " + (dir / "r.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out, "station: " + empty + ": the session has no views\n");
  r = run("run --quiet " + empty + " -o " + (dir / "run_empty").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out, "station: " + empty + ": the session has no views\n");
  // A folder without session.yaml given to run, as register says it.
  fs::create_directory(dir / "noyaml");
  r = run("run --quiet " + (dir / "noyaml").string() + " -o " + (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out, "station: " + (dir / "noyaml").string() + ": not a session folder (no session.yaml)\n");
  // An output inside a regular file.
  const std::string cloud = (dir / "cloud.ply").string();
  write_ply(cloud, test::fibonacci_sphere(300, 0.05));
  { std::ofstream(dir / "somefile") << "x"; }
  r = run("consolidate --json " + cloud + " -o " + (dir / "somefile" / "out.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(first_line(r).find((dir / "somefile").string() + " is a file, not a folder"), std::string::npos) << r.out;
  // A view file that is a folder.
  const std::string sess = (dir / "s").string();
  const std::string cloud2 = (dir / "cloud2.ply").string();
  write_ply(cloud2, test::fibonacci_sphere(300, 0.06));
  ASSERT_EQ(run("import " + cloud + " " + cloud2 + " -o " + sess).code, 0);
  fs::remove(sess + "/view_001.ply");
  fs::create_directory(sess + "/view_001.ply");
  r = run("register " + sess + " -o " + (dir / "r2.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find(sess + "/view_001.ply: view file is a folder"), std::string::npos) << r.out;
  // Too few points for a surface, in user terms and naming the file.
  Cloud one;
  one.points.emplace_back(0.f, 0.f, 0.f);
  write_ply(dir / "one.ply", one);
  r = run("reconstruct --json " + (dir / "one.ply").string() + " -o " + (dir / "o.ply").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_EQ(r.out, "station: " + (dir / "one.ply").string() +
                       ": 1 point: too few to reconstruct a surface from (at least 50 are needed)\n");
}

}  // namespace
}  // namespace station
