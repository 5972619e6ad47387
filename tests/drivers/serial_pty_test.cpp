// The real termios port against a pseudo-terminal whose master end a thread
// plays as the board: real open/tcsetattr/poll/read/write system calls, no
// hardware, no umockdev.
#include <gtest/gtest.h>

#include "core/error.h"
#include "drivers/fabscan_turntable.h"
#include "drivers/horus_turntable.h"
#include "drivers/serial_port.h"
#include "serial_boards.h"

namespace station {
namespace {

using testing::FabScanSim;
using testing::HorusSim;
using testing::PtyBoard;

std::string message(const std::function<void()>& f) {
  try {
    f();
  } catch (const DeviceError& e) {
    return e.what();
  }
  return "(no DeviceError)";
}

TEST(SerialPty, HorusOverRealTermios) {
  HorusSim sim;
  std::string received;
  {
    PtyBoard board(sim);
    const std::string uri = "horus:" + board.slave_path();
    HorusTurntable table(
        uri, board.slave_path(),
        horus_options(
            {{"steps", "200"}, {"microsteps", "16"}, {"speed", "1e4"}, {"settle_ms", "0"}}, uri),
        make_posix_serial_port());
    table.open();
    table.rotate_to(45);
    table.rotate_to(135);
    EXPECT_DOUBLE_EQ(table.angle(), 135.0);
    table.close();
    received = board.received();
  }  // board thread joined: sim is ours again
  EXPECT_EQ(received, "\x18M17\r\nG50\r\nG1F10000\r\nG1X45\r\nG1X135\r\nM18\r\n");
  EXPECT_DOUBLE_EQ(sim.x, 135.0);
  EXPECT_FALSE(sim.motor_on);
}

TEST(SerialPty, FabScanOverRealTermios) {
  FabScanSim sim;
  {
    PtyBoard board(sim);
    const std::string uri = "fabscan:" + board.slave_path();
    FabScanTurntable table(uri, board.slave_path(),
                           fabscan_options({{"steps", "200"}, {"microsteps", "16"}}, uri),
                           make_posix_serial_port());
    table.open();
    table.rotate_to(180);
    EXPECT_DOUBLE_EQ(table.angle(), 180.0);
  }
  EXPECT_EQ(sim.steps, 1600);
  EXPECT_FALSE(sim.motor_on);  // switched off by the destructor's close()
}

TEST(SerialPty, SecondOpenIsBusy) {
  HorusSim sim;
  PtyBoard board(sim);
  auto first = make_posix_serial_port();
  first->open(board.slave_path(), 115200);
  auto second = make_posix_serial_port();
  const std::string m = message([&] { second->open(board.slave_path(), 115200); });
  EXPECT_EQ(m, board.slave_path() + ": busy (another program has it open)");
  first->close();
  second->open(board.slave_path(), 115200);  // free again
}

TEST(SerialPty, UnplugDuringAMoveIsAReadError) {
  HorusSim sim;
  // Hang up once the first G1X has arrived: 1 + 5 + 5 + 8 handshake bytes, then "G1X..".
  PtyBoard board(sim, 21);
  const std::string uri = "horus:" + board.slave_path();
  HorusTurntable table(uri, board.slave_path(),
                       horus_options({{"steps", "200"}, {"timeout_ms", "5000"}}, uri),
                       make_posix_serial_port(), [](double) {});
  table.open();
  const std::string m = message([&] { table.rotate_to(90); });
  EXPECT_NE(m.find(board.slave_path()), std::string::npos) << m;
  EXPECT_NE(m.find("unplugged"), std::string::npos) << m;
  EXPECT_DOUBLE_EQ(table.angle(), 0.0);
}

TEST(SerialPty, SilentBoardTimesOut) {
  FabScanSim sim;
  sim.answers_ping = false;
  PtyBoard board(sim);
  const std::string uri = "fabscan:" + board.slave_path();
  FabScanTurntable table(uri, board.slave_path(),
                         fabscan_options({{"steps", "200"}, {"connect_timeout_ms", "300"}}, uri),
                         make_posix_serial_port());
  const std::string m = message([&] { table.open(); });
  EXPECT_NE(m.find(uri + ": no FabScan board answered the ping (210 -> 211) within 300 ms"),
            std::string::npos)
      << m;
}

TEST(SerialPty, MissingAndNonSerialPaths) {
  auto port = make_posix_serial_port();
  EXPECT_EQ(message([&] { port->open("/dev/ttyUSB-does-not-exist", 115200); }),
            "/dev/ttyUSB-does-not-exist: no such serial port (unplugged?)");
  EXPECT_NE(message([&] { port->open("/dev/null", 115200); }).find("/dev/null: not a serial port"),
            std::string::npos);
  EXPECT_THROW(baud_to_speed(12345), InvalidInput);
}

}  // namespace
}  // namespace station
