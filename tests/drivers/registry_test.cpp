#include "drivers/registry.h"

#include <gtest/gtest.h>

#include "core/error.h"

namespace station {
namespace {

class FakeTurntable : public Turntable {
 public:
  explicit FakeTurntable(std::string uri) : uri_(std::move(uri)) {}
  void open() override {}
  void close() override {}
  void home() override { angle_ = 0; }
  void rotate_to(double d) override { angle_ = d; }
  double angle() const override { return angle_; }
  int steps_per_revolution() const override { return 100; }
  std::string uri() const override { return uri_; }

 private:
  std::string uri_;
  double angle_ = 0;
};

TEST(DeviceUri, ParsesSchemePathAndOptions) {
  DeviceUri u = parse_device_uri("sim:synthetic?mesh=a%20b.ply&noise=0.001&color");
  EXPECT_EQ(u.scheme, "sim");
  EXPECT_EQ(u.path, "synthetic");
  EXPECT_EQ(u.options.at("mesh"), "a b.ply");
  EXPECT_EQ(u.options.at("noise"), "0.001");
  EXPECT_EQ(u.options.at("color"), "1");
}

TEST(DeviceUri, RejectsMalformed) {
  EXPECT_THROW(parse_device_uri("nocolon"), DeviceError);
  EXPECT_THROW(parse_device_uri(":x"), DeviceError);
  EXPECT_THROW(parse_device_uri("sim:x?a=%zz"), DeviceError);
  EXPECT_THROW(parse_device_uri("sim:x?=3"), DeviceError);
}

TEST(DeviceRegistry, MakesRegisteredAndRejectsUnknown) {
  DeviceRegistry reg;
  reg.add_turntable(
      "fake:table",
      [](const DeviceUri& u, DeviceContext&) { return std::make_unique<FakeTurntable>(u.text); },
      [] { return std::vector<DeviceInfo>{{"fake:table", DeviceKind::kTurntable, "fake"}}; });
  auto t = reg.make_turntable("fake:table?x=1");
  ASSERT_TRUE(t);
  t->rotate_to(30);
  EXPECT_DOUBLE_EQ(t->angle(), 30);
  EXPECT_EQ(t->uri(), "fake:table?x=1");
  try {
    reg.make_scanner("fake:table");
    FAIL() << "a turntable entry must not make a scanner";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("fake:table: unknown scanner"), std::string::npos);
  }
  EXPECT_THROW(reg.make_turntable("usb:nothing"), DeviceError);
  ASSERT_EQ(reg.list().size(), 1u);
  EXPECT_EQ(reg.list()[0].uri, "fake:table");
}

TEST(DeviceRegistry, SchemeWideEntryMatchesAnyPathButExactWins) {
  DeviceRegistry reg;
  int which = 0;
  reg.add_turntable("fake:", [&](const DeviceUri& u, DeviceContext&) {
    which = 1;
    return std::make_unique<FakeTurntable>(u.text);
  }, nullptr);
  reg.add_turntable("fake:special", [&](const DeviceUri& u, DeviceContext&) {
    which = 2;
    return std::make_unique<FakeTurntable>(u.text);
  }, nullptr);
  reg.make_turntable("fake:/dev/ttyUSB0");
  EXPECT_EQ(which, 1);
  reg.make_turntable("fake:special");
  EXPECT_EQ(which, 2);
}

}  // namespace
}  // namespace station
