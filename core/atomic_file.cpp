#include "core/atomic_file.h"

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <streambuf>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

#include "core/error.h"

namespace station {

namespace {

namespace fs = std::filesystem;

/// A write-only streambuf over a POSIX descriptor. iostreams hide errno, and we
/// need it (ENOSPC, EDQUOT, EFBIG...) for a useful message, so we do the
/// write(2) calls ourselves and remember the first failure.
class FdStreambuf : public std::streambuf {
 public:
  explicit FdStreambuf(int fd) : fd_(fd), buf_(1 << 16) { setp(buf_.data(), buf_.data() + buf_.size()); }
  int error() const { return errno_; }

 protected:
  int_type overflow(int_type ch) override {
    if (!flush_buffer()) return traits_type::eof();
    if (!traits_type::eq_int_type(ch, traits_type::eof())) {
      *pptr() = traits_type::to_char_type(ch);
      pbump(1);
    }
    return traits_type::not_eof(ch);
  }

  int sync() override { return flush_buffer() ? 0 : -1; }

  std::streamsize xsputn(const char* s, std::streamsize n) override {
    // Large writes bypass the buffer.
    if (n >= static_cast<std::streamsize>(buf_.size())) {
      if (!flush_buffer() || !write_all(s, static_cast<std::size_t>(n))) return 0;
      return n;
    }
    return std::streambuf::xsputn(s, n);
  }

 private:
  bool flush_buffer() {
    const std::size_t n = static_cast<std::size_t>(pptr() - pbase());
    const bool ok = write_all(pbase(), n);
    setp(buf_.data(), buf_.data() + buf_.size());
    return ok;
  }

  bool write_all(const char* p, std::size_t n) {
    if (errno_ != 0) return false;
    while (n > 0) {
      const ssize_t w = ::write(fd_, p, n);
      if (w < 0) {
        if (errno == EINTR) continue;
        errno_ = errno;
        return false;
      }
      if (w == 0) {  // should not happen for regular files; treat as a full disk
        errno_ = ENOSPC;
        return false;
      }
      p += w;
      n -= static_cast<std::size_t>(w);
    }
    return true;
  }

  int fd_;
  std::vector<char> buf_;
  int errno_ = 0;
};

[[noreturn]] void fail(const fs::path& path, const std::string& problem, int err) {
  std::string msg = path.string() + ": " + problem;
  if (err != 0) msg += std::string(": ") + std::strerror(err);
  throw IoError(msg);
}

// The paths an interrupt handler removes (remove_unfinished_outputs): per kind, fixed
// slots of lock-free pointers to strings their owners keep alive while registered.
enum class Kind : int { kTemporary = 0, kFile = 1, kFolder = 2 };
constexpr int kSlots = 128;
std::atomic<const char*> g_paths[3][kSlots];
static_assert(std::atomic<const char*>::is_always_lock_free, "the interrupt handler needs lock-free pointers");

/// The slot (kind * kSlots + index), or -1 when all are taken (that path is then left
/// to the normal exit paths).
int register_path(const char* p, Kind kind) {
  for (int k = 0; k < kSlots; ++k) {
    const char* expected = nullptr;
    if (g_paths[int(kind)][k].compare_exchange_strong(expected, p)) return int(kind) * kSlots + k;
  }
  return -1;
}
// Set while remove_unfinished_outputs runs: an owner taking its path out of the list
// waits for the sweep before it frees the string (the handler may run on another
// thread, and may have read the pointer just before).
std::atomic<bool> g_sweeping{false};
static_assert(std::atomic<bool>::is_always_lock_free, "the interrupt handler needs a lock-free flag");

void unregister_path(int slot) {
  if (slot < 0) return;
  g_paths[slot / kSlots][slot % kSlots].store(nullptr);
  while (g_sweeping.load()) std::this_thread::yield();
}

/// Removes the temporary on every exit path unless released.
struct TempGuard {
  std::string path;
  int fd = -1;
  bool armed = true;
  int slot = -1;
  TempGuard(std::string p, int f) : path(std::move(p)), fd(f) { slot = register_path(path.c_str(), Kind::kTemporary); }
  ~TempGuard() {
    unregister_path(slot);
    if (fd >= 0) ::close(fd);
    if (armed) ::unlink(path.c_str());
  }
};

}  // namespace

namespace {

/// Refuses an output name that is taken by something other than a regular file or a
/// symbolic link (a device, FIFO, socket, folder: the rename would replace it), and a
/// folder that is missing or a file. A link is replaced by the file, as a regular file
/// is; what it pointed to stays untouched (a link into a recorded session must not
/// become a way to overwrite it).
void check_target(const fs::path& path) {
  if (path.empty()) throw IoError("(empty path): cannot write");
  std::error_code ec;
  const fs::file_status st = fs::symlink_status(path, ec);
  if (fs::exists(st) && !fs::is_regular_file(st) && !fs::is_symlink(st))
    throw IoError(path.string() + ": cannot write: " +
                  (fs::is_directory(st) ? std::string("it is a folder") : std::string("not a regular file (a device, FIFO or socket)")) +
                  "; name a file");
  const fs::path dir = path.has_parent_path() ? path.parent_path() : fs::path(".");
  if (!fs::is_directory(dir, ec)) {
    if (fs::exists(dir, ec))
      throw IoError(path.string() + ": cannot write: " + dir.string() + " is a file, not a folder");
    throw IoError(path.string() + ": cannot write: folder " + dir.string() + " does not exist");
  }
}

}  // namespace

void check_output_path(const fs::path& path) {
  check_target(path);
  const fs::path dir = path.has_parent_path() ? path.parent_path() : fs::path(".");
  if (::access(dir.c_str(), W_OK) != 0) fail(path, "cannot write into folder " + dir.string(), errno);
}

void write_file_atomic(const fs::path& path, const std::function<void(std::ostream&)>& fill) {
  check_target(path);
  const fs::path dir = path.has_parent_path() ? path.parent_path() : fs::path(".");

  static std::atomic<unsigned> counter{0};
  const std::string tmp = path.string() + ".tmp-" + std::to_string(::getpid()) + "-" +
                          std::to_string(counter.fetch_add(1));
  // O_EXCL: never clobber (or follow a symlink at) a name someone else owns.
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) fail(path, "cannot create temporary file", errno);
  TempGuard guard{tmp, fd};

  {
    FdStreambuf buf(fd);
    std::ostream out(&buf);
    // A throwing fill propagates as is; the guard removes the temporary and the
    // old file stays untouched.
    fill(out);
    out.flush();
    if (buf.error() != 0) fail(path, "write failed", buf.error());
    if (!out) fail(path, "write failed (stream error)", 0);
  }
  if (::fsync(fd) != 0) fail(path, "fsync failed", errno);
  const int fd_to_close = guard.fd;
  guard.fd = -1;
  if (::close(fd_to_close) != 0) fail(path, "close failed", errno);
  // (An interrupt between the rename and the release would remove the new name's
  // temporary, which no longer exists: harmless.)
  if (::rename(tmp.c_str(), path.c_str()) != 0) fail(path, "cannot rename temporary into place", errno);
  guard.armed = false;

  // Make the rename itself durable; failure here is not worth an error (the data is written).
  const int dfd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    ::fsync(dfd);
    ::close(dfd);
  }
}

void write_file_atomic(const fs::path& path, std::string_view bytes) {
  write_file_atomic(path, [bytes](std::ostream& out) {
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  });
}

CreatedOutputs::CreatedOutputs(const fs::path& dir, const std::vector<fs::path>& files) {
  std::error_code ec;
  for (const fs::path& f : files)
    if (!f.empty() && fs::symlink_status(f, ec).type() == fs::file_type::not_found) files_.push_back(f);
  if (!dir.empty()) {
    fs::path p = fs::absolute(dir, ec).lexically_normal();
    if (!ec) {
      if (p.filename().empty()) p = p.parent_path();
      while (!p.empty() && fs::symlink_status(p, ec).type() == fs::file_type::not_found) {
        folders_.push_back(p);
        if (p == p.parent_path()) break;
        p = p.parent_path();
      }
    }
  }
  // (files_ and folders_ are not changed again until keep() or the destructor, which
  // take these pointers out of the list first.)
  for (const fs::path& f : files_) slots_.push_back(register_path(f.c_str(), Kind::kFile));
  for (const fs::path& d : folders_) slots_.push_back(register_path(d.c_str(), Kind::kFolder));
}

void remove_unfinished_outputs() noexcept {
  g_sweeping.store(true);
  for (const Kind kind : {Kind::kTemporary, Kind::kFile})
    for (std::atomic<const char*>& slot : g_paths[int(kind)])
      if (const char* p = slot.exchange(nullptr)) ::unlink(p);
  // Folders only when empty; a few passes, so a parent emptied by removing its child
  // goes too, whatever order their slots are in.
  for (int pass = 0; pass < 8; ++pass)
    for (std::atomic<const char*>& slot : g_paths[int(Kind::kFolder)])
      if (const char* p = slot.load()) ::rmdir(p);
  g_sweeping.store(false);
}

void CreatedOutputs::keep() {
  for (int s : slots_) unregister_path(s);
  slots_.clear();
  folders_.clear();
  files_.clear();
}

CreatedOutputs::~CreatedOutputs() {
  for (int s : slots_) unregister_path(s);
  std::error_code ec;
  for (const fs::path& f : files_) fs::remove(f, ec);
  for (const fs::path& d : folders_) {
    if (!fs::is_directory(d, ec) || !fs::is_empty(d, ec) || ec) break;
    fs::remove(d, ec);
  }
}

}  // namespace station
