#pragma once
// Crash-safe file writes: the content goes to "PATH.tmp-<pid>-<n>" in the same
// folder, is flushed and fsync'ed, then renamed over PATH. A reader therefore
// sees the old file or the new one, never a half-written one; on any failure
// (full disk, unwritable folder) the temporary is removed and IoError names PATH.
#include <filesystem>
#include <functional>
#include <ostream>
#include <string_view>

namespace station {

/// Calls `fill` with a binary stream into a temporary file, then renames it to `path`.
void write_file_atomic(const std::filesystem::path& path,
                       const std::function<void(std::ostream&)>& fill);

/// Convenience: atomically writes `bytes` to `path`.
void write_file_atomic(const std::filesystem::path& path, std::string_view bytes);

}  // namespace station
