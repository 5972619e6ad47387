// `station serve`'s API (station/serve.h) against an in-process server on a free
// loopback port, with a small, slow simulated profile (views wait 0.4 s each) so
// that jobs are still running while a test pokes at them.
#include <gtest/gtest.h>

#include <chrono>
#include <cstring>
#include <fstream>
#include <thread>

#include "capture/session.h"
#include "core/error.h"
#include "core/io.h"
#include "station/jobs.h"
#include "station/serve.h"
#include "test_util.h"

// Last: cpp-httplib brings <resolv.h>, whose _res macro breaks Eigen's headers.
#include <httplib.h>
#include <nlohmann/json.hpp>

namespace station {
namespace {

namespace fs = std::filesystem;
using Json = nlohmann::json;
using namespace std::chrono_literals;

void write_text(const fs::path& p, const std::string& text) {
  std::ofstream(p) << text;
}

/// A profile scanning the bundled bottle small and slowly: 160x120 pixels, `views`
/// views, `settle` seconds after each turn.
std::string slow_profile(int views, double settle) {
  const fs::path mesh = test::source_dir() / "data" / "mustard_bottle" / "textured.obj";
  return "scanner:\n  uri: sim:synthetic\n  options:\n    mesh: " + mesh.string() +
         "\n    width: \"160\"\n    height: \"120\"\n    seed: \"3\"\n"
         "turntable:\n  uri: sim:turntable\n"
         "capture:\n  views: " + std::to_string(views) + "\n  settle_s: " + std::to_string(settle) +
         "\nreconstruct:\n  resolution: 48\n";
}

class ServeTest : public ::testing::Test {
 protected:
  void start(ServeOptions extra = {}) {
    fs::create_directories(dir_ / "profiles");
    write_text(dir_ / "profiles" / "slow.yaml", slow_profile(6, 0.4));
    write_text(dir_ / "profiles" / "quick.yaml", slow_profile(4, 0));
    ServeOptions o = extra;
    o.port = 0;
    o.data_dir = dir_ / "data";
    o.profile_dir = dir_ / "profiles";
    o.threads = 2;
    server_ = std::make_unique<StationServer>(o);
    thread_ = std::thread([this] { server_->listen(); });
    client_ = std::make_unique<httplib::Client>("127.0.0.1", server_->port());
    client_->set_read_timeout(60, 0);
    for (int k = 0; k < 100 && !client_->Get("/api/status"); ++k) std::this_thread::sleep_for(20ms);
  }
  void TearDown() override {
    if (server_) server_->stop();
    if (thread_.joinable()) thread_.join();
    server_.reset();
  }
  httplib::Result post(const std::string& path, const Json& body) {
    return client_->Post(path.c_str(), body.dump(), "application/json");
  }
  static Json json(const httplib::Result& r) { return Json::parse(r->body); }

  /// Reads the job's event stream to its end; the events as JSON.
  std::vector<Json> events_to_end(const std::string& id) {
    std::string text;
    auto r = client_->Get(("/api/jobs/" + id + "/events").c_str(), [&](const char* data, std::size_t n) {
      text.append(data, n);
      return true;
    });
    EXPECT_TRUE(r) << "the event stream broke";
    std::vector<Json> out;
    std::size_t pos = 0;
    while ((pos = text.find("data: ", pos)) != std::string::npos) {
      const std::size_t end = text.find('\n', pos);
      out.push_back(Json::parse(text.substr(pos + 6, end - pos - 6)));
      pos = end;
    }
    return out;
  }
  Json wait_job(const std::string& id) {
    for (int k = 0; k < 6000; ++k) {
      const Json j = json(client_->Get(("/api/jobs/" + id).c_str()));
      if (j["state"] != "running") return j;
      std::this_thread::sleep_for(20ms);
    }
    ADD_FAILURE() << "job " << id << " did not end";
    return {};
  }

  test::TempDir dir_{"station-serve"};
  std::unique_ptr<StationServer> server_;
  std::unique_ptr<httplib::Client> client_;
  std::thread thread_;
};

TEST_F(ServeTest, ServesThePageAndLists) {
  start();
  auto page = client_->Get("/");
  ASSERT_TRUE(page);
  EXPECT_EQ(page->status, 200);
  EXPECT_NE(page->body.find("Turntable station"), std::string::npos);
  auto three = client_->Get("/vendor/three/build/three.module.js");
  ASSERT_TRUE(three);
  EXPECT_EQ(three->status, 200);
  const Json profiles = json(client_->Get("/api/profiles"));
  ASSERT_EQ(profiles["profiles"].size(), 2u);
  EXPECT_EQ(profiles["profiles"][0]["name"], "quick.yaml");
  EXPECT_EQ(profiles["profiles"][0]["views"], 4);
  const Json devices = json(client_->Get("/api/devices"));
  bool sim = false;
  for (const Json& d : devices["devices"]) sim |= d["uri"].get<std::string>().rfind("sim:", 0) == 0;
  EXPECT_TRUE(sim);
  EXPECT_EQ(json(client_->Get("/api/sessions"))["sessions"].size(), 0u);
  auto unknown = client_->Get("/api/nothing");
  ASSERT_TRUE(unknown);
  EXPECT_EQ(unknown->status, 404);
  EXPECT_TRUE(json(unknown).contains("error"));
}

TEST_F(ServeTest, BadRequestsGetOneLineErrors) {
  start();
  auto bad = client_->Post("/api/scan", "{\"session\": ", "application/json");
  ASSERT_TRUE(bad);
  EXPECT_EQ(bad->status, 400);
  EXPECT_NE(json(bad)["error"].get<std::string>().find("not valid JSON"), std::string::npos);
  auto array = client_->Post("/api/scan", "[1, 2]", "application/json");
  EXPECT_EQ(array->status, 400);
  auto type = post("/api/scan", {{"views", "twelve"}});
  EXPECT_EQ(type->status, 400);
  EXPECT_NE(json(type)["error"].get<std::string>().find("views"), std::string::npos);
  auto text = client_->Post("/api/scan", "{}", "text/plain");
  EXPECT_EQ(text->status, 415);
  auto name = post("/api/scan", {{"session", "a b"}, {"profile", "quick.yaml"}});
  EXPECT_EQ(name->status, 400);
  auto profile = post("/api/scan", {{"session", "x"}, {"profile", "../profiles/quick.yaml"}});
  EXPECT_EQ(profile->status, 400);
  EXPECT_NE(json(profile)["error"].get<std::string>().find("profile"), std::string::npos);
  // A client picks a device the station offers, never a URI of its own.
  auto uri = post("/api/scan", {{"session", "x"}, {"profile", "quick.yaml"}, {"scanner", "sim:synthetic?mesh=/etc/passwd"}});
  EXPECT_EQ(uri->status, 400);
  EXPECT_FALSE(fs::exists(dir_ / "data" / "x"));
  auto missing = client_->Get("/api/sessions/nosuch");
  EXPECT_EQ(missing->status, 404);
  EXPECT_NE(json(missing)["error"].get<std::string>().find("nosuch"), std::string::npos);
  EXPECT_EQ(post("/api/run", {{"session", "nosuch"}})->status, 404);
  EXPECT_EQ(post("/api/scan", {{"session", "nosuch"}, {"resume", true}})->status, 404);
  EXPECT_EQ(client_->Get("/api/jobs/99")->status, 404);
  EXPECT_EQ(post("/api/jobs/99/stop", Json::object())->status, 404);
  // Another site's page cannot drive the station: not from its origin, nor by a
  // rebound host name.
  auto origin = client_->Post("/api/scan", {{"Origin", "http://evil.example"}}, "{}", "application/json");
  EXPECT_EQ(origin->status, 403);
  auto host = client_->Get("/api/sessions", {{"Host", "evil.example"}});
  EXPECT_EQ(host->status, 403);
}

TEST_F(ServeTest, NothingOutsideTheDataFolderCanBeRead) {
  start();
  write_text(dir_ / "secret.txt", "TOP-SECRET-CONTENT");
  write_text(dir_ / "data" / "secret.txt", "TOP-SECRET-CONTENT");
  auto id = json(post("/api/scan", {{"session", "s1"}, {"profile", "quick.yaml"}, {"run", false}}))["job"];
  EXPECT_EQ(wait_job(id)["state"], "finished");
  auto ok = client_->Get("/api/sessions/s1/files/session.yaml");
  ASSERT_TRUE(ok);
  EXPECT_EQ(ok->status, 200);
  fs::create_symlink(dir_ / "secret.txt", dir_ / "data" / "s1" / "link.txt");
  for (const char* path : {"/api/sessions/s1/files/../secret.txt", "/api/sessions/s1/files/../../secret.txt",
                           "/api/sessions/s1/files/%2e%2e/%2e%2e/secret.txt", "/api/sessions/s1/files/..%2Fsecret.txt",
                           "/api/sessions/s1/files/link.txt", "/api/sessions/s1/files//etc/passwd",
                           "/api/sessions/../files/secret.txt", "/api/sessions/%2e%2e/files/secret.txt",
                           "/api/sessions/s1/files/.hidden", "/../secret.txt", "/%2e%2e/secret.txt"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_GE(r->status, 400) << path;
    EXPECT_EQ(r->body.find("TOP-SECRET"), std::string::npos) << path << ": " << r->body;
  }
}

TEST_F(ServeTest, BeyondLoopbackOnlyWithItsToken) {
  ServeOptions o;
  o.bind = "0.0.0.0";
  o.port = 0;
  o.data_dir = dir_ / "d0";
  EXPECT_THROW(StationServer{o}, InvalidInput);
  write_text(dir_ / "short.txt", "abc\n");
  o.token_file = dir_ / "short.txt";
  EXPECT_THROW(StationServer{o}, InvalidInput);

  const std::string token = "0123456789abcdef-station";
  write_text(dir_ / "token.txt", token + "\n");
  ServeOptions t;
  t.bind = "0.0.0.0";
  t.token_file = dir_ / "token.txt";
  start(t);
  auto none = client_->Get("/api/sessions");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->status, 401);
  EXPECT_EQ(client_->Get("/api/sessions", {{"X-Station-Token", token + "x"}})->status, 403);
  EXPECT_EQ(client_->Get("/api/sessions", {{"X-Station-Token", "0123456789abcdef-statioN"}})->status, 403);
  EXPECT_EQ(client_->Post("/api/scan", "{}", "application/json")->status, 401);
  EXPECT_EQ(client_->Get("/api/sessions", {{"X-Station-Token", token}})->status, 200);
  EXPECT_EQ(client_->Get("/api/sessions", {{"Authorization", "Bearer " + token}})->status, 200);
  EXPECT_EQ(client_->Get("/api/sessions", {{"Cookie", "a=b; station_token=" + token}})->status, 200);
  // With a token the page's name for the host may be anything.
  EXPECT_EQ(client_->Get("/api/sessions", {{"X-Station-Token", token}, {"Host", "bench.lab:8080"}})->status, 200);
  // The page itself is public (it asks for the token).
  EXPECT_EQ(client_->Get("/")->status, 200);
}

TEST_F(ServeTest, SecondJobOnABusyDeviceIsRefused) {
  start();
  const auto first = post("/api/scan", {{"session", "a"}, {"profile", "slow.yaml"}, {"run", false}});
  ASSERT_EQ(first->status, 202) << first->body;
  const std::string id = json(first)["job"];
  const auto second = post("/api/scan", {{"session", "b"}, {"profile", "slow.yaml"}, {"run", false}});
  ASSERT_EQ(second->status, 409);
  EXPECT_NE(json(second)["error"].get<std::string>().find("in use by job " + id), std::string::npos);
  EXPECT_FALSE(fs::exists(dir_ / "data" / "b"));
  // Nor a run of the session being scanned, nor a preview of the busy scanner.
  EXPECT_EQ(post("/api/run", {{"session", "a"}})->status, 409);
  EXPECT_EQ(client_->Get("/api/preview.png?profile=slow.yaml")->status, 409);
  EXPECT_EQ(post("/api/scan", {{"session", "a"}, {"profile", "slow.yaml"}})->status, 409);
  EXPECT_EQ(wait_job(id)["state"], "finished");
  // Free again: the preview is a PNG of the depth map and the colour image.
  auto preview = client_->Get("/api/preview.png?profile=slow.yaml");
  ASSERT_EQ(preview->status, 200) << preview->body;
  EXPECT_EQ(preview->body.substr(1, 3), "PNG");
  EXPECT_EQ(preview->get_header_value("Content-Type"), "image/png");
  const auto third = post("/api/scan", {{"session", "b"}, {"profile", "slow.yaml"}, {"run", false}, {"views", 2}});
  ASSERT_EQ(third->status, 202) << third->body;
  EXPECT_EQ(wait_job(json(third)["job"])["state"], "finished");
  EXPECT_EQ(json(client_->Get("/api/sessions/b"))["views"], 2);
}

// A scan job whose first view fails leaves no session (its stub made the next try
// "exists already").
TEST_F(ServeTest, AScanWhoseFirstViewFailsLeavesNoSession) {
  const fs::path src = dir_ / "recorded";
  {
    Session rec = Session::create(src, SessionManifest{});
    Cloud c;
    for (int i = 0; i < 50; ++i) c.points.push_back(Vec3f(0.01f * float(i), 0, 0.5f));
    rec.add_view(c, ViewRecord{});
  }
  const std::string view = (src / "view_000.ply").string();
  const std::string whole = read_file_bytes(view);
  std::ofstream(view, std::ios::binary) << whole.substr(0, whole.size() / 2);
  fs::create_directories(dir_ / "profiles");
  write_text(dir_ / "profiles" / "broken.yaml",
             "scanner:\n  uri: sim:replay\n  options:\n    session: " + src.string() +
                 "\nturntable:\n  uri: sim:turntable\ncapture:\n  views: 2\n");
  start();
  for (int attempt = 0; attempt < 2; ++attempt) {
    const auto r = post("/api/scan", {{"session", "x"}, {"profile", "broken.yaml"}, {"run", false}});
    ASSERT_EQ(r->status, 202) << attempt << ": " << r->body;
    const Json j = wait_job(json(r)["job"]);
    EXPECT_EQ(j["state"], "failed") << j.dump();
    EXPECT_NE(j.dump().find("nothing was recorded"), std::string::npos) << j.dump();
    EXPECT_FALSE(fs::exists(dir_ / "data" / "x")) << attempt;
  }
}

TEST_F(ServeTest, StoppedScanResumesToTheSameSession) {
  start();
  const std::string id = json(post("/api/scan", {{"session", "r"}, {"profile", "slow.yaml"}, {"run", false}}))["job"];
  // Wait for the first view, then stop: the scan ends after the view in progress.
  for (int k = 0; k < 500 && json(client_->Get("/api/sessions/r")).value("views", 0) < 1; ++k)
    std::this_thread::sleep_for(20ms);
  ASSERT_EQ(post("/api/jobs/" + id + "/stop", Json::object())->status, 200);
  const Json stopped = wait_job(id);
  EXPECT_EQ(stopped["state"], "stopped");
  const int kept = json(client_->Get("/api/sessions/r"))["views"];
  EXPECT_GE(kept, 1);
  EXPECT_LT(kept, 6);
  const auto resumed = post("/api/scan", {{"session", "r"}, {"resume", true}, {"run", false}, {"profile", "slow.yaml"}});
  ASSERT_EQ(resumed->status, 202) << resumed->body;
  const std::vector<Json> ev = events_to_end(json(resumed)["job"]);
  ASSERT_FALSE(ev.empty());
  EXPECT_EQ(ev.back()["type"], "end");
  EXPECT_EQ(ev.back()["state"], "finished");
  int views = 0;
  for (const Json& e : ev)
    if (e["type"] == "view") {
      EXPECT_GE(e["view"].get<int>(), kept);  // resumed where it stopped
      ++views;
    }
  EXPECT_EQ(views, 6 - kept);
  const Json d = json(client_->Get("/api/sessions/r"));
  EXPECT_EQ(d["views"], 6);
  EXPECT_TRUE(d["files"]["merged.ply"].get<bool>());
}

TEST_F(ServeTest, ClientDroppingMidRunDoesNotStopIt) {
  start();
  const std::string scan = json(post("/api/scan", {{"session", "m"}, {"profile", "quick.yaml"}, {"run", false}}))["job"];
  EXPECT_EQ(wait_job(scan)["state"], "finished");
  const auto run = post("/api/run", {{"session", "m"}, {"profile", "quick.yaml"}});
  ASSERT_EQ(run->status, 202) << run->body;
  const std::string id = json(run)["job"];
  // Read the stream until the first event, then hang up.
  std::string first;
  auto r = client_->Get(("/api/jobs/" + id + "/events").c_str(), [&](const char* data, std::size_t n) {
    first.append(data, n);
    return false;
  });
  EXPECT_FALSE(r);  // cancelled by us
  EXPECT_NE(first.find("data: "), std::string::npos);
  const Json done = wait_job(id);
  EXPECT_EQ(done["state"], "finished") << done.dump();
  const Json d = json(client_->Get("/api/sessions/m"));
  EXPECT_TRUE(d["files"]["run/mesh.ply"].get<bool>());
  ASSERT_EQ(d["stages"].size(), 3u);
  const Json reg = d["stages"][0];
  EXPECT_EQ(reg["name"], "register");
  EXPECT_EQ(reg["view_prior"].size(), 4u);
  // The whole stream read again from the start: every stage started and done, in order.
  std::vector<std::string> stages;
  for (const Json& e : events_to_end(id))
    if (e["type"] == "stage") stages.push_back(e["stage"].get<std::string>() + ":" + e["status"].get<std::string>());
  EXPECT_EQ(stages, (std::vector<std::string>{"register:start", "register:done", "consolidate:start",
                                              "consolidate:done", "surface:start", "surface:done"}));
  // Results: the mesh as OBJ, the registered cloud with one index per view.
  auto obj = client_->Get("/api/sessions/m/mesh.obj");
  ASSERT_EQ(obj->status, 200);
  EXPECT_NE(obj->body.find("\nf "), std::string::npos);
  auto cloud = client_->Get("/api/sessions/m/cloud?max=1000");
  ASSERT_EQ(cloud->status, 200);
  ASSERT_GE(cloud->body.size(), 8u);
  std::uint32_t n = 0, views = 0;
  std::memcpy(&n, cloud->body.data(), 4);
  std::memcpy(&views, cloud->body.data() + 4, 4);
  EXPECT_GT(n, 100u);
  EXPECT_LE(n, 1000u + 4u);
  EXPECT_EQ(views, 4u);
  EXPECT_EQ(cloud->body.size(), 8u + 17u * n);  // xyz, view, rgb
  // A second run without resume would redo the finished one: refused; with resume, kept.
  EXPECT_EQ(post("/api/run", {{"session", "m"}, {"profile", "quick.yaml"}})->status, 400);
  const auto again = post("/api/run", {{"session", "m"}, {"profile", "quick.yaml"}, {"resume", true}});
  ASSERT_EQ(again->status, 202);
  int kept = 0;
  for (const Json& e : events_to_end(json(again)["job"]))
    if (e["type"] == "stage" && e["status"] == "kept") ++kept;
  EXPECT_EQ(kept, 3);
}

// A data folder that cannot be made: the reason is the file system's, not the "no such
// file" that follows from it (a read-only mount said "No such file or directory").
TEST(ServeData, AFolderThatCannotBeMadeSaysWhy) {
  try {
    JobManager jobs("/sys/station-serve-test/data", "", 1);
    ADD_FAILURE() << "a data folder under /sys was made";
  } catch (const IoError& e) {
    // EPERM for root, EACCES for anyone else, EROFS where /sys is mounted read-only.
    const std::string msg = e.what(), head = "/sys/station-serve-test/data: cannot create the data folder: ";
    EXPECT_TRUE(msg == head + "Operation not permitted" || msg == head + "Permission denied" ||
                msg == head + "Read-only file system")
        << msg;
  }
}

TEST(ServeTokens, LoopbackAddresses) {
  EXPECT_TRUE(is_loopback_address("127.0.0.1"));
  EXPECT_TRUE(is_loopback_address("127.1.2.3"));
  EXPECT_TRUE(is_loopback_address("::1"));
  EXPECT_TRUE(is_loopback_address("localhost"));
  EXPECT_FALSE(is_loopback_address("0.0.0.0"));
  EXPECT_FALSE(is_loopback_address("192.168.1.5"));
  EXPECT_FALSE(is_loopback_address("::"));
  EXPECT_FALSE(is_loopback_address("128.0.0.1"));
  EXPECT_FALSE(is_loopback_address("localhost.evil.example"));
}

}  // namespace
}  // namespace station
