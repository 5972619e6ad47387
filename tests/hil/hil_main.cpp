// main() of hil_tests: exit code 77 ("skipped" for ctest's SKIP_RETURN_CODE)
// when every test skipped because no device was found.
#include <gtest/gtest.h>

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  const int rc = RUN_ALL_TESTS();
  const auto* unit = ::testing::UnitTest::GetInstance();
  if (rc != 0) return rc;
  if (unit->successful_test_count() == 0 && unit->skipped_test_count() > 0) return 77;
  return 0;
}
