#pragma once
// Thread counts and stage timings as every stage reads them.
#include <chrono>

namespace station {

/// Worker threads for a `threads` parameter: 0 means all the cores TBB may use, a
/// positive count is that many. Negative counts are the caller's to reject (with the
/// caller's name in the message).
int worker_threads(int threads);

/// The most threads a command line or profile may ask for: more is no machine's,
/// and asked of TBB it starts that many workers (thousands stalled `fit`).
inline constexpr int kMaxThreads = 1024;

/// Seconds on the steady clock since `t0`.
inline double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace station
