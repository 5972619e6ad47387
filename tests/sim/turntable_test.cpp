#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "core/error.h"
#include "sim/sim.h"
#include "sim_test_util.h"

namespace station {
namespace {

std::unique_ptr<Turntable> open_table(DeviceRegistry& reg, const std::string& uri) {
  auto t = reg.make_turntable(uri);
  t->open();
  return t;
}

TEST(SimTurntable, DefaultsAndHome) {
  DeviceRegistry reg = test::sim_registry();
  auto t = open_table(reg, "sim:turntable");
  EXPECT_EQ(t->steps_per_revolution(), 3200);
  EXPECT_EQ(t->uri(), "sim:turntable");
  EXPECT_EQ(t->angle(), 0.0);
  t->rotate_to(123.4);
  t->home();
  EXPECT_EQ(t->angle(), 0.0);
}

TEST(SimTurntable, QuantisesToStepsAndWraps) {
  DeviceRegistry reg = test::sim_registry();
  auto t = open_table(reg, "sim:turntable?steps=8");  // 45 degree steps
  EXPECT_EQ(t->steps_per_revolution(), 8);
  const std::pair<double, double> cases[] = {{100, 90},   {112.6, 135}, {-90, 270},  {-1, 0},
                                             {359, 0},    {765, 45},    {-720, 0},   {22.4, 0},
                                             {22.6, 45},  {1e12, 270},    {337.6, 0}};
  for (auto [ask, expect] : cases) {
    t->rotate_to(ask);
    EXPECT_DOUBLE_EQ(t->angle(), expect) << ask;
    EXPECT_GE(t->angle(), 0.0);
    EXPECT_LT(t->angle(), 360.0);
  }
  auto fine = open_table(reg, "sim:turntable?steps=3200");
  fine->rotate_to(45);
  EXPECT_DOUBLE_EQ(fine->angle(), 45.0);  // 400 steps exactly
  fine->rotate_to(30);                    // 266.67 steps -> 267 steps
  EXPECT_NEAR(fine->angle(), 267 * 360.0 / 3200, 1e-12);
  fine->rotate_to(359.99);
  EXPECT_EQ(fine->angle(), 0.0);
}

TEST(SimTurntable, RejectsNonFiniteAnglesAndBadOptions) {
  DeviceRegistry reg = test::sim_registry();
  auto t = open_table(reg, "sim:turntable");
  t->rotate_to(90);
  EXPECT_THROW(t->rotate_to(std::nan("")), DeviceError);
  EXPECT_THROW(t->rotate_to(std::numeric_limits<double>::infinity()), DeviceError);
  EXPECT_EQ(t->angle(), 90.0);  // unchanged
  EXPECT_THROW(reg.make_turntable("sim:turntable?speed=3"), DeviceError);
  EXPECT_THROW(reg.make_turntable("sim:turntable?steps=0"), DeviceError);
  EXPECT_THROW(reg.make_turntable("sim:turntable?steps=many"), DeviceError);
  auto closed = reg.make_turntable("sim:turntable");
  EXPECT_THROW(closed->rotate_to(10), DeviceError);
  EXPECT_THROW(closed->home(), DeviceError);
}

TEST(SimTurntable, TablesOfOneRegistryShareTheBench) {
  DeviceRegistry reg = test::sim_registry();
  auto a = open_table(reg, "sim:turntable");
  auto b = open_table(reg, "sim:turntable");
  a->rotate_to(90);
  EXPECT_EQ(b->angle(), 90.0);
  DeviceRegistry other = test::sim_registry();
  EXPECT_EQ(open_table(other, "sim:turntable")->angle(), 0.0);
}

TEST(SimRegistry, ListsTheSimDevices) {
  DeviceRegistry reg = test::sim_registry();
  bool synthetic = false, replay = false, table = false;
  for (const DeviceInfo& d : reg.list()) {
    synthetic |= d.uri.rfind("sim:synthetic", 0) == 0 && d.kind == DeviceKind::kScanner;
    replay |= d.uri.rfind("sim:replay", 0) == 0 && d.kind == DeviceKind::kScanner;
    table |= d.uri.rfind("sim:turntable", 0) == 0 && d.kind == DeviceKind::kTurntable;
    EXPECT_FALSE(d.description.empty());
  }
  EXPECT_TRUE(synthetic);
  EXPECT_TRUE(replay);
  EXPECT_TRUE(table);
  EXPECT_EQ(reg.make_scanner("sim:synthetic?mesh=m.ply")->uri(), "sim:synthetic?mesh=m.ply");
}

}  // namespace
}  // namespace station
