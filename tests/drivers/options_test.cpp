// The option readers every driver shares (drivers/options.h).
#include "drivers/options.h"

#include <gtest/gtest.h>

#include "core/error.h"

namespace station {
namespace {

TEST(DeviceOptions, ParseNumberTakesOnlyAWholeFiniteNumber) {
  double v = -1;
  EXPECT_TRUE(parse_number("2.5e-3", v));
  EXPECT_DOUBLE_EQ(v, 2.5e-3);
  for (const char* bad : {"", "1x", "1 ", "nan", "inf", "1e999", "0x", "--1"}) {
    v = 7;
    EXPECT_FALSE(parse_number(bad, v)) << bad;
    EXPECT_EQ(v, 7) << bad;
  }
}

TEST(DeviceOptions, NumberListsHaveTheirCountAndNothingElse) {
  const std::string uri = "v4l2:/dev/video0";
  EXPECT_TRUE(option_numbers({}, "extrinsics", 3, "x,y,z", uri).empty());
  EXPECT_EQ(option_numbers({{"e", "1,2,3"}}, "e", 3, "x,y,z", uri), (std::vector<double>{1, 2, 3}));
  for (const char* bad : {"1,2", "1,2,3,4", "1,2,", "1,,3", "1,b,3", ""}) {
    try {
      option_numbers({{"e", bad}}, "e", 3, "x,y,z", uri);
      ADD_FAILURE() << "accepted '" << bad << "'";
    } catch (const DeviceError& e) {
      const std::string what = e.what();
      EXPECT_EQ(what.rfind(uri + ": option e: expected 3 comma-separated numbers (x,y,z), got '", 0), 0u) << what;
    }
  }
  Intrinsics k;
  k.distortion[0] = 9;
  option_distortion({}, "distortion", k, uri);
  EXPECT_EQ(k.distortion[0], 9);  // absent: untouched
  option_distortion({{"distortion", "0.1,-0.2,0,0,0.05"}}, "distortion", k, uri);
  EXPECT_DOUBLE_EQ(k.distortion[1], -0.2);
  EXPECT_DOUBLE_EQ(k.distortion[4], 0.05);
}

}  // namespace
}  // namespace station
