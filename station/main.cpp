#include <sys/auxv.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <string>

#include "station/cli.h"

namespace {

// glibc backs large malloc blocks with transparent huge pages only when the
// glibc.malloc.hugetlb tunable asks for it, and reads tunables at start-up only. With
// it the surface stage takes about a tenth of the page faults (mustard 100k: 140 k ->
// 15 k over three runs) and the stages run 5-25 % faster on our VM, for 6-11 % more
// peak memory (docs/run.md, "Huge pages"); the output is the same. So the station
// starts itself once more with it set, unless the environment already sets
// GLIBC_TUNABLES (the user's choice stands) or STATION_HUGE_PAGES=0. The restarted
// process gets STATION_HUGE_PAGES=0 too, so it never restarts again. Not done for a
// privileged (AT_SECURE) process, whose tunables glibc ignores, nor when this binary
// was not started directly (a loader, valgrind or an emulator: /proc/self/exe then
// names that program, not the one AT_EXECFN names). A failed exec goes on as before.
void restart_with_huge_pages(char** argv) {
  if (std::getenv("GLIBC_TUNABLES") || getauxval(AT_SECURE)) return;
  const char* choice = std::getenv("STATION_HUGE_PAGES");
  if (choice && std::strcmp(choice, "0") == 0) return;
  const bool had_choice = choice != nullptr;
  const std::string previous = had_choice ? choice : "";  // setenv may free what getenv gave
  const auto* started = reinterpret_cast<const char*>(getauxval(AT_EXECFN));
  struct stat self {}, named {};
  if (!started || stat("/proc/self/exe", &self) != 0 || stat(started, &named) != 0 || self.st_dev != named.st_dev ||
      self.st_ino != named.st_ino)
    return;
  if (setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1", 0) != 0) return;
  if (setenv("STATION_HUGE_PAGES", "0", 1) != 0) {
    unsetenv("GLIBC_TUNABLES");
    return;
  }
  execv("/proc/self/exe", argv);
  unsetenv("GLIBC_TUNABLES");
  if (had_choice) {
    setenv("STATION_HUGE_PAGES", previous.c_str(), 1);
  } else {
    unsetenv("STATION_HUGE_PAGES");
  }
}

}  // namespace

int main(int argc, char** argv) {
  restart_with_huge_pages(argv);
  return station::run_cli(argc, argv);
}
