#include <unistd.h>

#include <cstdlib>
#include <cstring>

#include "station/cli.h"

namespace {

// glibc backs large malloc blocks with transparent huge pages only when the
// glibc.malloc.hugetlb tunable asks for it, and reads tunables at start-up only. With
// it the surface stage takes about a tenth of the page faults (mustard 100k: 140 k ->
// 15 k over three runs; docs/run.md, "Huge pages"), and a run is 10-20 % faster. So the
// station starts itself once more with it set, unless the environment already sets
// GLIBC_TUNABLES (the user's choice stands) or STATION_HUGE_PAGES=0 (e.g. under
// valgrind, whose tool /proc/self/exe then names). Nothing else changes: a failed exec
// goes on as before.
void restart_with_huge_pages(char** argv) {
  if (std::getenv("GLIBC_TUNABLES")) return;
  const char* choice = std::getenv("STATION_HUGE_PAGES");
  if (choice && std::strcmp(choice, "0") == 0) return;
  if (setenv("GLIBC_TUNABLES", "glibc.malloc.hugetlb=1", 0) != 0) return;
  execv("/proc/self/exe", argv);
  unsetenv("GLIBC_TUNABLES");
}

}  // namespace

int main(int argc, char** argv) {
  restart_with_huge_pages(argv);
  return station::run_cli(argc, argv);
}
