#pragma once
// Crash-safe file writes: the content goes to "PATH.tmp-<pid>-<n>" in the same
// folder, is flushed and fsync'ed, then renamed over PATH. A reader therefore
// sees the old file or the new one, never a half-written one; on any failure
// (full disk, unwritable folder) the temporary is removed and IoError names PATH.
#include <filesystem>
#include <functional>
#include <ostream>
#include <string_view>
#include <vector>

namespace station {

/// Calls `fill` with a binary stream into a temporary file, then renames it to `path`.
/// A `path` taken by something other than a regular file or a symbolic link (a device,
/// a FIFO, a socket, a folder) is refused, never replaced; a link is replaced by the
/// file (what it pointed to stays untouched).
void write_file_atomic(const std::filesystem::path& path,
                       const std::function<void(std::ostream&)>& fill);

/// What write_file_atomic would refuse, checked before a command does its work: the
/// folder of `path` missing, a file, or not writable; `path` a device, FIFO, socket or
/// folder. Throws IoError naming `path`.
void check_output_path(const std::filesystem::path& path);

/// Convenience: atomically writes `bytes` to `path`.
void write_file_atomic(const std::filesystem::path& path, std::string_view bytes);

/// For an interrupt handler (SIGINT, SIGTERM), async-signal-safe: removes the
/// temporaries of the writes in progress and what the live CreatedOutputs would
/// remove on failure (their new files, then their folders still empty). The
/// process must end right after it (_Exit): the writes in progress are cut off.
void remove_unfinished_outputs() noexcept;

/// What a command is about to create for its output: the folders of `dir` (and its
/// parents) that do not exist yet, and the files of `files` that do not. Unless
/// kept, the destructor (a failed command) removes those files, then those folders
/// that are still empty, deepest first; what existed before is never touched.
class CreatedOutputs {
 public:
  explicit CreatedOutputs(const std::filesystem::path& dir, const std::vector<std::filesystem::path>& files = {});
  ~CreatedOutputs();
  CreatedOutputs(const CreatedOutputs&) = delete;
  CreatedOutputs& operator=(const CreatedOutputs&) = delete;
  /// The command succeeded: everything stays.
  void keep();

 private:
  std::vector<std::filesystem::path> folders_, files_;
  std::vector<int> slots_;  ///< their places in the interrupt handler's list
};

}  // namespace station
