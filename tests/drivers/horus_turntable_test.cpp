#include "drivers/horus_turntable.h"

#include <gtest/gtest.h>

#include "core/error.h"
#include "serial_boards.h"

namespace station {
namespace {

using testing::HorusSim;
using testing::ScriptedPort;

struct Bench {
  HorusSim sim;
  ScriptedPort* port = nullptr;
  std::vector<double> sleeps;
  std::unique_ptr<HorusTurntable> table;
  explicit Bench(const DeviceOptions& o = {
                     {"steps", "200"}, {"microsteps", "16"}, {"speed", "45"}}) {
    auto p = std::make_unique<ScriptedPort>(sim);
    port = p.get();
    const std::string uri = "horus:/dev/ttyUSB7";
    table =
        std::make_unique<HorusTurntable>(uri, "/dev/ttyUSB7", horus_options(o, uri), std::move(p),
                                         [this](double s) { sleeps.push_back(s); });
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

TEST(HorusTurntable, HandshakeThenMotorOnOriginAndSpeed) {
  Bench b;
  b.table->open();
  EXPECT_EQ(b.port->baud, 115200);
  EXPECT_EQ(b.port->written.substr(0, 1), "\x18");
  EXPECT_EQ(b.sim.commands, (std::vector<std::string>{"M17", "G50", "G1F45"}));
  EXPECT_TRUE(b.sim.motor_on);
  EXPECT_EQ(b.table->steps_per_revolution(), 3200);
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
  b.table->close();
  EXPECT_FALSE(b.sim.motor_on);  // M18 on close
  EXPECT_FALSE(b.port->is_open());
}

TEST(HorusTurntable, AbsoluteMovesGoForwardAndWaitTheMoveTime) {
  Bench b;
  b.table->open();
  b.table->rotate_to(90);
  EXPECT_EQ(b.sim.commands.back(), "G1X90");
  EXPECT_DOUBLE_EQ(b.table->angle(), 90.0);
  ASSERT_EQ(b.sleeps.size(), 1u);
  EXPECT_NEAR(b.sleeps[0], 90.0 / 45.0 + 0.1, 1e-9);  // move time at 45 deg/s + settle
  b.table->rotate_to(45);                             // forwards through 360: motor at 405 degrees
  EXPECT_EQ(b.sim.commands.back(), "G1X405");
  EXPECT_DOUBLE_EQ(b.table->angle(), 45.0);
  EXPECT_NEAR(b.sleeps[1], 315.0 / 45.0 + 0.1, 1e-9);
  b.table->rotate_to(405);  // same place, wrapped: no command
  EXPECT_EQ(b.sim.commands.back(), "G1X405");
}

TEST(HorusTurntable, AngleIsQuantizedToWholeSteps) {
  Bench b(DeviceOptions{{"steps", "200"}});  // 1.8 degrees a step
  b.table->open();
  b.table->rotate_to(10);  // 5.56 steps -> 6 steps = 10.8 degrees
  EXPECT_EQ(b.sim.commands.back(), "G1X10.8");
  EXPECT_NEAR(b.table->angle(), 10.8, 1e-9);
}

TEST(HorusTurntable, DirectionFromTheProfile) {
  Bench b(DeviceOptions{{"steps", "200"}, {"microsteps", "16"}, {"direction", "cw"}});
  b.table->open();
  b.table->rotate_to(90);
  EXPECT_EQ(b.sim.commands.back(), "G1X-90");
  EXPECT_DOUBLE_EQ(b.table->angle(), 90.0);
}

TEST(HorusTurntable, HomeReturnsForwardsToTheOriginAndResetsIt) {
  Bench b;
  b.table->open();
  b.table->rotate_to(100);
  b.table->home();
  const auto& c = b.sim.commands;
  ASSERT_GE(c.size(), 2u);
  EXPECT_EQ(c[c.size() - 2], "G1X360");
  EXPECT_EQ(c.back(), "G50");
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
  b.table->rotate_to(22.5);
  EXPECT_EQ(c.back(), "G1X22.5");  // from the new origin
}

TEST(HorusTurntable, StepsAreRequiredAndOptionsChecked) {
  EXPECT_NE(message([] { horus_options({}, "horus:/dev/ttyUSB0"); }).find("'steps'"),
            std::string::npos);
  EXPECT_NE(message([] {
              horus_options({{"steps", "200"}, {"speeed", "3"}}, "horus:/dev/ttyUSB0");
            }).find("unknown option 'speeed'"),
            std::string::npos);
  EXPECT_NE(message([] {
              horus_options({{"steps", "abc"}}, "horus:/x");
            }).find("steps=abc"),
            std::string::npos);
  EXPECT_NE(message([] {
              horus_options({{"steps", "200"}, {"direction", "up"}}, "horus:/x");
            }).find("direction=up"),
            std::string::npos);
  EXPECT_NE(message([] {
              horus_options({{"steps", "200"}, {"baud", "1234"}}, "horus:/x");
            }).find("1234"),
            std::string::npos);
}

TEST(HorusTurntable, WrongFirmwareHasNoBanner) {
  Bench b;
  b.sim.banner = "Grbl 0.9j ['$' for help]";
  const std::string m = message([&] { b.table->open(); });
  EXPECT_NE(m.find("horus:/dev/ttyUSB7: no Horus banner"), std::string::npos) << m;
  EXPECT_NE(m.find("Grbl 0.9j"), std::string::npos) << m;
  EXPECT_FALSE(b.port->is_open());
}

TEST(HorusTurntable, GarbageBeforeTheBannerIsIgnored) {
  Bench b;
  b.port->extra_input = std::string("\xff\x01\x80noise\r\n", 9);
  b.sim.noise_before_banner = "\x7f\x7f";
  b.table->open();
  b.table->rotate_to(45);
  EXPECT_DOUBLE_EQ(b.table->angle(), 45.0);
}

TEST(HorusTurntable, ErrorAnswerNamesTheCommand) {
  Bench b;
  b.sim.answers = {{"G1X", "error: Bad number format"}};
  b.table->open();
  const std::string m = message([&] { b.table->rotate_to(90); });
  EXPECT_NE(m.find("horus:/dev/ttyUSB7: board answered 'error: Bad number format' to 'G1X90'"),
            std::string::npos)
      << m;
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);  // not reached
}

TEST(HorusTurntable, SilentBoardTimesOutAndClosesUntilReopened) {
  Bench b;
  b.sim.answers = {{"G1X", ""}};
  b.table->open();
  const std::string m = message([&] { b.table->rotate_to(90); });
  EXPECT_NE(
      m.find("no answer to 'G1X90' within 2000 ms; port closed, open() again to resynchronise"),
      std::string::npos)
      << m;
  EXPECT_DOUBLE_EQ(b.table->angle(), 0.0);
  EXPECT_FALSE(b.port->is_open());  // a late "ok" must not answer the next command
  EXPECT_NE(message([&] { b.table->rotate_to(90); }).find("before open"), std::string::npos);
  b.sim.answers.clear();
  b.table->open();  // Ctrl-X, banner, fresh origin
  b.table->rotate_to(90);
  EXPECT_EQ(b.sim.commands.back(), "G1X90");
  EXPECT_DOUBLE_EQ(b.table->angle(), 90.0);
}

TEST(HorusTurntable, UnplugMidScanKeepsTheLastReachedAngle) {
  Bench b;
  b.table->open();
  b.table->rotate_to(45);
  b.port->unplug_after_writes = b.port->writes;  // cable pulled now
  const std::string m = message([&] { b.table->rotate_to(60); });
  EXPECT_NE(m.find("unplugged"), std::string::npos) << m;
  EXPECT_DOUBLE_EQ(b.table->angle(), 45.0);
  b.table->close();  // no throw although the port is gone
}

TEST(HorusTurntable, UseBeforeOpenIsAnError) {
  Bench b;
  EXPECT_NE(message([&] { b.table->rotate_to(10); }).find("before open"), std::string::npos);
  b.port->fail_open = true;
  EXPECT_NE(message([&] { b.table->open(); }).find("/dev/ttyUSB7"), std::string::npos);
}

}  // namespace
}  // namespace station
