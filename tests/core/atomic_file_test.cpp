#include "core/atomic_file.h"

#include <gtest/gtest.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

namespace fs = std::filesystem;

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::size_t entries(const fs::path& dir) {
  std::size_t n = 0;
  for (auto it = fs::directory_iterator(dir); it != fs::directory_iterator(); ++it) ++n;
  return n;
}

TEST(AtomicFile, WritesContentAndLeavesNoTemporary) {
  test::TempDir dir;
  const fs::path p = dir / "out.bin";
  std::string bytes = "hello";
  bytes.push_back('\0');
  bytes += std::string(200000, 'x');  // larger than the internal buffer
  write_file_atomic(p, bytes);
  EXPECT_EQ(slurp(p), bytes);
  EXPECT_EQ(entries(dir.path()), 1u);

  write_file_atomic(p, [](std::ostream& out) { out << "second " << 42; });
  EXPECT_EQ(slurp(p), "second 42");
  EXPECT_EQ(entries(dir.path()), 1u);
}

TEST(AtomicFile, ThrowingFillKeepsOldFile) {
  test::TempDir dir;
  const fs::path p = dir / "keep.txt";
  write_file_atomic(p, std::string_view("old content"));
  EXPECT_THROW(write_file_atomic(p,
                                 [](std::ostream& out) {
                                   out << std::string(100000, 'n');
                                   throw std::runtime_error("generator failed");
                                 }),
               std::runtime_error);
  EXPECT_EQ(slurp(p), "old content");
  EXPECT_EQ(entries(dir.path()), 1u);
}

TEST(AtomicFile, StreamFailureIsAnIoError) {
  test::TempDir dir;
  const fs::path p = dir / "bad.txt";
  EXPECT_THROW(write_file_atomic(p, [](std::ostream& out) { out.setstate(std::ios::badbit); }),
               IoError);
  EXPECT_FALSE(fs::exists(p));
  EXPECT_EQ(entries(dir.path()), 0u);
}

TEST(AtomicFile, MissingFolderIsAnIoErrorNamingIt) {
  test::TempDir dir;
  const fs::path p = dir / "no_such_folder" / "x.ply";
  try {
    write_file_atomic(p, std::string_view("data"));
    FAIL() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find((dir / "no_such_folder").string()), std::string::npos)
        << e.what();
  }
  EXPECT_EQ(entries(dir.path()), 0u);
}

// A device or FIFO at the output's name was replaced by a regular file (as root,
// --poses-out /dev/full replaced the device): refused now. A symbolic link is replaced
// by the file, never written through (it may point into a recorded session).
TEST(AtomicFile, SpecialFilesAreRefusedAndLinksReplaced) {
  test::TempDir dir;
  const fs::path fifo = dir / "pipe.yaml";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0666), 0);
  try {
    write_file_atomic(fifo, std::string_view("data"));
    FAIL() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_NE(std::string(e.what()).find("not a regular file"), std::string::npos) << e.what();
  }
  EXPECT_THROW(check_output_path(fifo), IoError);
  EXPECT_TRUE(fs::is_fifo(fs::symlink_status(fifo)));
  // A link to a file: the link becomes the file; the file it pointed to keeps its content.
  const fs::path target = dir / "real.yaml", link = dir / "link.yaml";
  write_file_atomic(target, std::string_view("old"));
  fs::create_symlink("real.yaml", link);
  check_output_path(link);
  write_file_atomic(link, std::string_view("new"));
  EXPECT_FALSE(fs::is_symlink(fs::symlink_status(link)));
  const auto first_line = [](const fs::path& p) {
    std::ifstream in(p);
    std::string got;
    std::getline(in, got);
    return got;
  };
  EXPECT_EQ(first_line(target), "old");
  EXPECT_EQ(first_line(link), "new");
  // A link to a FIFO is replaced too (the FIFO stays).
  fs::create_symlink("pipe.yaml", dir / "to_pipe.yaml");
  write_file_atomic(dir / "to_pipe.yaml", std::string_view("x"));
  EXPECT_TRUE(fs::is_fifo(fs::symlink_status(fifo)));
  // A missing folder is found before any work.
  EXPECT_THROW(check_output_path(dir / "no_such_folder" / "x.ply"), IoError);
  check_output_path(dir / "fresh.ply");
  EXPECT_FALSE(fs::exists(dir / "fresh.ply"));
}

// What an interrupt handler calls (station's SIGINT/SIGTERM): the write in progress
// loses its temporary (the write then fails, the old file untouched), and what a live
// CreatedOutputs made goes, its folders only once empty; before, a Ctrl-C left the
// temporary "PATH.tmp-<pid>-<n>" next to the output.
TEST(AtomicFile, AnInterruptRemovesTheTemporaryAndTheCreatedOutputs) {
  test::TempDir dir;
  const fs::path out = dir / "mesh.ply";
  write_file_atomic(out, std::string_view("old"));
  std::size_t during = 0;
  EXPECT_THROW(write_file_atomic(out,
                                 [&](std::ostream& o) {
                                   o << "new";
                                   during = entries(dir.path());  // mesh.ply and its temporary
                                   remove_unfinished_outputs();
                                 }),
               IoError);
  EXPECT_EQ(during, 2u);
  EXPECT_EQ(entries(dir.path()), 1u);
  EXPECT_EQ(slurp(out), "old");
  {
    const fs::path made = dir / "a" / "b", file = dir / "a" / "b" / "merged.ply", other = dir / "poses.yaml";
    CreatedOutputs created(made, {file, other});
    fs::create_directories(made);
    write_file_atomic(file, std::string_view("x"));
    write_file_atomic(other, std::string_view("y"));
    remove_unfinished_outputs();
    EXPECT_FALSE(fs::exists(dir / "a"));
    EXPECT_FALSE(fs::exists(other));
    EXPECT_TRUE(fs::exists(out));
  }
  {
    // Outputs without a folder of their own (register's two files, parameterise's).
    CreatedOutputs created({}, {dir / "merged.ply", dir / "poses.yaml"});
    write_file_atomic(dir / "merged.ply", std::string_view("x"));
    remove_unfinished_outputs();
    EXPECT_FALSE(fs::exists(dir / "merged.ply"));
  }
  {
    // Kept outputs are not the handler's any more.
    CreatedOutputs created(dir / "c", {dir / "c" / "kept.ply"});
    fs::create_directories(dir / "c");
    write_file_atomic(dir / "c" / "kept.ply", std::string_view("x"));
    created.keep();
    remove_unfinished_outputs();
    EXPECT_TRUE(fs::exists(dir / "c" / "kept.ply"));
  }
}

TEST(AtomicFile, RenameOntoFolderFailsCleanly) {
  test::TempDir dir;
  fs::create_directories(dir / "occupied" / "inner");
  try {
    write_file_atomic(dir / "occupied", std::string_view("data"));
    FAIL() << "expected IoError";
  } catch (const IoError& e) {
    EXPECT_EQ(std::string(e.what()).rfind((dir / "occupied").string(), 0), 0u) << e.what();
  }
  EXPECT_EQ(entries(dir.path()), 1u);  // only the folder; the temporary is gone
}

TEST(AtomicFile, FullDiskIsDetected) {
  // Simulate a full disk in a child process: a file-size limit makes write(2)
  // fail with EFBIG once SIGXFSZ is ignored.
  test::TempDir dir;
  const fs::path p = dir / "big.bin";
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    std::signal(SIGXFSZ, SIG_IGN);
    rlimit lim{4096, 4096};
    setrlimit(RLIMIT_FSIZE, &lim);
    int code = 1;
    try {
      write_file_atomic(p, std::string(1 << 20, 'z'));
      code = 2;  // no error: wrong
    } catch (const IoError& e) {
      const std::string msg = e.what();
      code = (msg.rfind(p.string(), 0) == 0 && msg.find("large") != std::string::npos) ? 0 : 3;
    } catch (...) {
      code = 4;
    }
    _exit(code);
  }
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_FALSE(fs::exists(p));
  EXPECT_EQ(entries(dir.path()), 0u);
}

}  // namespace
}  // namespace station
