#include "core/threads.h"

#include <tbb/task_arena.h>

namespace station {

int worker_threads(int threads) { return threads == 0 ? tbb::this_task_arena::max_concurrency() : threads; }

}  // namespace station
