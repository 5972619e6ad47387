#include "drivers/fabscan_turntable.h"

#include <gtest/gtest.h>

#include <numeric>

#include "core/error.h"
#include "serial_boards.h"

namespace station {
namespace {

using testing::FabScanSim;
using testing::ScriptedPort;

struct Bench {
  FabScanSim sim;
  ScriptedPort* port = nullptr;
  std::unique_ptr<FabScanTurntable> table;
  explicit Bench(DeviceOptions o = {{"steps", "200"}, {"microsteps", "16"}}) {
    o.emplace("connect_timeout_ms", "30");
    auto p = std::make_unique<ScriptedPort>(sim);
    port = p.get();
    const std::string uri = "fabscan:/dev/ttyACM3";
    table = std::make_unique<FabScanTurntable>(uri, "/dev/ttyACM3", fabscan_options(o, uri),
                                               std::move(p));
  }
};

std::string message(const std::function<void()>& f) {
  try {
    f();
  } catch (const DeviceError& e) {
    return e.what();
  }
  return "(no DeviceError)";
}

std::string bytes(std::initializer_list<int> b) {
  std::string s;
  for (int v : b) s.push_back(static_cast<char>(v));
  return s;
}

TEST(FabScanTurntable, OpenPingsSelectsTheTableStepperAndSwitchesItOn) {
  Bench b;
  b.table->open();
  EXPECT_EQ(b.port->baud, 9600);
  EXPECT_EQ(b.port->written, bytes({210, 212, 10, 205, 204, 210}));
  EXPECT_TRUE(b.sim.motor_on);
  EXPECT_EQ(b.sim.selected, 10);
  EXPECT_EQ(b.table->steps_per_revolution(), 3200);
  b.table->close();
  EXPECT_FALSE(b.sim.motor_on);
}

TEST(FabScanTurntable, MovesInChunksOfAtMost255StepsAndConfirmsWithAPing) {
  Bench b;
  b.table->open();
  b.table->rotate_to(90);  // 800 microsteps of 3200
  EXPECT_EQ(b.sim.step_bytes, (std::vector<int>{255, 255, 255, 35}));
  EXPECT_EQ(b.sim.steps, 800);
  EXPECT_DOUBLE_EQ(b.table->angle(), 90.0);
  b.table->rotate_to(45);  // forwards through 360: 2800 more
  EXPECT_EQ(b.sim.steps, 3600);
  EXPECT_DOUBLE_EQ(b.table->angle(), 45.0);
  b.table->home();
  EXPECT_EQ(b.sim.steps % 3200, 0);
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
}

TEST(FabScanTurntable, StepsPerRevolutionComeFromTheProfile) {
  Bench b(
      DeviceOptions{{"steps", "400"}, {"microsteps", "4"}});  // 1600 per turn, not the usual 3200
  b.table->open();
  b.table->rotate_to(90);
  EXPECT_EQ(b.sim.steps, 400);
  EXPECT_EQ(b.table->steps_per_revolution(), 1600);
  Bench c(DeviceOptions{{"steps", "200"}});
  c.table->open();
  c.table->rotate_to(10);  // 5.56 steps -> 6
  EXPECT_EQ(c.sim.steps, 6);
  EXPECT_NEAR(c.table->angle(), 10.8, 1e-9);
}

TEST(FabScanTurntable, ClockwiseWiring) {
  Bench b(DeviceOptions{{"steps", "200"}, {"microsteps", "16"}, {"direction", "cw"}});
  b.table->open();
  EXPECT_EQ(b.sim.direction, -1);
  b.table->rotate_to(90);
  EXPECT_EQ(b.sim.steps, -800);              // motor turned the other way ...
  EXPECT_DOUBLE_EQ(b.table->angle(), 90.0);  // ... so the table turned +90
}

TEST(FabScanTurntable, NoPongIsAClearError) {
  Bench b;
  b.sim.answers_ping = false;
  const std::string m = message([&] { b.table->open(); });
  EXPECT_NE(m.find("fabscan:/dev/ttyACM3: no FabScan board answered the ping"), std::string::npos)
      << m;
  EXPECT_FALSE(b.port->is_open());
}

TEST(FabScanTurntable, WrongAnswerByteIsReported) {
  Bench b;
  b.sim.pong_byte = 85;
  const std::string m = message([&] { b.table->open(); });
  EXPECT_NE(m.find("got byte 85"), std::string::npos) << m;
}

TEST(FabScanTurntable, MoveNotConfirmedWhenUnpluggedMidMove) {
  Bench b;
  b.table->open();
  b.port->unplug_after_writes = b.port->writes + 1;  // the step bytes go out, the ping does not
  const std::string m = message([&] { b.table->rotate_to(90); });
  EXPECT_NE(m.find("/dev/ttyACM3"), std::string::npos) << m;
  EXPECT_NE(m.find("unplugged"), std::string::npos) << m;
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
}

TEST(FabScanTurntable, MoveNotConfirmedInTimeClosesThePort) {
  Bench b;
  b.table->open();
  b.sim.answers_ping = false;  // the table jams: no pong after the steps
  const std::string m = message([&] { b.table->rotate_to(90); });
  EXPECT_NE(m.find("no pong (211) to ping (210) within"), std::string::npos) << m;
  EXPECT_NE(m.find("port closed"), std::string::npos) << m;
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
  EXPECT_FALSE(b.port->is_open());
  b.sim.answers_ping = true;
  b.table->open();
  b.table->rotate_to(45);
  EXPECT_DOUBLE_EQ(b.table->angle(), 45.0);
}

TEST(FabScanTurntable, OptionsChecked) {
  EXPECT_NE(message([] {
              fabscan_options({{"microsteps", "16"}}, "fabscan:/x");
            }).find("'steps'"),
            std::string::npos);
  EXPECT_NE(message([] {
              fabscan_options({{"steps", "0"}}, "fabscan:/x");
            }).find("steps=0"),
            std::string::npos);
}

}  // namespace
}  // namespace station
