// Failure handling of the DML: injected backend faults, a real full file system, bad
// directories, short transfers, and stale private directory cleanup.
#include "StorageTestUtil.h"

#include "sipmss/storage/DML.h"
#include "sipmss/storage/DMLTesting.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <string>
#include <sys/mount.h>
#include <sys/wait.h>
#include <unistd.h>
#include <vector>

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::ListDir;
using sipmss::storage::testing::TempDir;

// Wraps the POSIX backend; fails the n-th read or write (counting from 1) with a chosen errno.
class FaultBackend : public FileBackend
{
public:
  struct Plan
  {
    int failWriteAt = 0; // 0: never
    int failReadAt = 0;
    int error = EIO;
    bool failRemove = false;
    int writes = 0;
    int reads = 0;
  };
  explicit FaultBackend(Plan* plan) : plan_(plan), posix_(FileBackend::CreatePosix()) {}
  int Create(const std::string& path) override { return this->posix_->Create(path); }
  void Close(int h) override { this->posix_->Close(h); }
  void Remove(const std::string& path) override
  {
    if (this->plan_->failRemove)
    {
      throw StorageError("injected remove failure", path, EBUSY);
    }
    this->posix_->Remove(path);
  }
  void ReadAt(int h, void* dst, std::size_t n, std::uint64_t off) override
  {
    if (++this->plan_->reads == this->plan_->failReadAt)
    {
      throw StorageError("injected read failure", "", this->plan_->error);
    }
    this->posix_->ReadAt(h, dst, n, off);
  }
  void WriteAt(int h, const void* src, std::size_t n, std::uint64_t off) override
  {
    if (++this->plan_->writes == this->plan_->failWriteAt)
    {
      throw StorageError("injected write failure", "", this->plan_->error);
    }
    this->posix_->WriteAt(h, src, n, off);
  }
  void Truncate(int h, std::uint64_t n) override { this->posix_->Truncate(h, n); }

private:
  Plan* plan_;
  std::unique_ptr<FileBackend> posix_;
};

Profile OutOfCore(const std::string& dir, std::uint64_t budget = 64 * 1024)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = ModePolicy::OutOfCore;
  return p;
}

void ExpectMentions(const StorageError& e, const std::string& path, int error)
{
  EXPECT_EQ(e.OsError(), error);
  EXPECT_NE(e.Path().find(path), std::string::npos) << e.Path();
  const std::string what = e.what();
  EXPECT_NE(what.find(e.Path()), std::string::npos) << what;
  EXPECT_NE(what.find(std::strerror(error)), std::string::npos) << what;
}

TEST(StorageFault, FailingWriteIsReportedAndNothingIsLost)
{
  TempDir tmp;
  FaultBackend::Plan plan;
  {
    DML dml(std::make_unique<FaultBackend>(&plan));
    dml.Config(OutOfCore(tmp.Path()));
    Array<std::uint32_t> a(dml, 200000);
    plan.failWriteAt = 10; // a write-back during eviction
    bool thrown = false;
    std::uint32_t i = 0;
    try
    {
      for (; i < 200000; ++i)
      {
        a.Set(i, i + 1);
      }
    }
    catch (const StorageError& e)
    {
      thrown = true;
      ExpectMentions(e, tmp.Path(), EIO);
      EXPECT_NE(std::string(e.what()).find(".blk"), std::string::npos);
    }
    ASSERT_TRUE(thrown);
    // The failed page stayed cached and dirty: continue and verify every element.
    for (; i < 200000; ++i)
    {
      a.Set(i, i + 1);
    }
    for (std::uint32_t k = 0; k < 200000; ++k)
    {
      ASSERT_EQ(a.Get(k), k + 1) << k;
    }
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

TEST(StorageFault, FailingReadAndInjectedENOSPC)
{
  TempDir tmp;
  {
    FaultBackend::Plan plan;
    DML dml(std::make_unique<FaultBackend>(&plan));
    dml.Config(OutOfCore(tmp.Path()));
    Array<std::uint64_t> a(dml, 100000);
    for (std::uint64_t i = 0; i < 100000; ++i)
    {
      a.Set(i, i);
    }
    plan.failReadAt = plan.reads + 3;
    try
    {
      for (std::uint64_t i = 0; i < 100000; ++i)
      {
        ASSERT_EQ(a.Get(i), i);
      }
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      ExpectMentions(e, dml.PrivateDirectory(), EIO);
    }
    for (std::uint64_t i = 0; i < 100000; i += 11)
    {
      ASSERT_EQ(a.Get(i), i);
    }
  }
  {
    FaultBackend::Plan plan;
    plan.error = ENOSPC;
    plan.failWriteAt = 1;
    DML dml(std::make_unique<FaultBackend>(&plan));
    dml.Config(OutOfCore(tmp.Path()));
    const std::uint32_t pattern = 0xDEADBEEF;
    const BlockId id = dml.OpenBlock(4, 100000);
    try
    {
      dml.Fill(id, &pattern); // writes uncached pages directly
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      ExpectMentions(e, tmp.Path(), ENOSPC);
    }
  }
  {
    // A remove that fails while closing: reported, and the destructor still cleans up.
    FaultBackend::Plan plan;
    DML dml(std::make_unique<FaultBackend>(&plan));
    dml.Config(OutOfCore(tmp.Path()));
    const BlockId id = dml.OpenBlock(4, 1000);
    plan.failRemove = true;
    EXPECT_THROW(dml.CloseBlock(id), StorageError);
    EXPECT_THROW(dml.Count(id), std::invalid_argument); // closed anyway
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

TEST(StorageFault, RealENOSPCOnTinyTmpfs)
{
  TempDir tmp;
  const std::string mnt = tmp.Path() + "/mnt";
  ASSERT_EQ(::mkdir(mnt.c_str(), 0700), 0);
  if (::mount("tmpfs", mnt.c_str(), "tmpfs", 0, "size=1m") != 0)
  {
    GTEST_SKIP() << "cannot mount a 1 MiB tmpfs here: " << std::strerror(errno);
  }
  {
    // 8 MiB of data on a 1 MiB file system: refused when the block is opened, before the disk
    // fills, naming the directory, its room and the option.
    DML dml;
    dml.Config(OutOfCore(mnt));
    bool thrown = false;
    try
    {
      Array<std::uint64_t> a(dml, 1 << 20);
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      thrown = true;
      ExpectMentions(e, mnt, ENOSPC);
      EXPECT_NE(std::string(e.what()).find("1.0 MiB free, 8.0 MiB needed"), std::string::npos)
        << e.what();
      EXPECT_NE(std::string(e.what()).find("--tmpdir"), std::string::npos) << e.what();
    }
    EXPECT_TRUE(thrown);
    EXPECT_EQ(dml.GetStats().fileBytes, 0u);
  }
  {
    // Another process takes the room after the block was opened: the write fails with ENOSPC,
    // and with no other directory that is the error.
    DML dml;
    dml.Config(OutOfCore(mnt));
    Array<std::uint64_t> a(dml, 96 * 1024); // 768 KiB
    {
      std::ofstream fill(mnt + "/other", std::ios::binary);
      fill << std::string(900 * 1024, 'x');
    }
    bool thrown = false;
    try
    {
      const std::vector<std::uint64_t> data(a.Size(), 7); // whole pages go straight to the file
      a.Write(0, data.size(), data.data());
    }
    catch (const StorageError& e)
    {
      thrown = true;
      ExpectMentions(e, mnt, ENOSPC);
    }
    EXPECT_TRUE(thrown);
    ::unlink((mnt + "/other").c_str());
  }
  EXPECT_TRUE(ListDir(mnt).empty());
  ::umount2(mnt.c_str(), MNT_DETACH);
}

TEST(StorageFault, MissingAndUnwritableDirectories)
{
  TempDir tmp;
  {
    const std::string missing = tmp.Path() + "/does/not/exist";
    DML dml;
    dml.Config(OutOfCore(missing));
    try
    {
      dml.OpenBlock(4, 10);
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      ExpectMentions(e, missing, ENOENT);
    }
    // The DML stays usable after the failure.
    EXPECT_EQ(dml.GetMode(), Mode::OutOfCore);
  }
  {
    // chmod does not stop root: a directory under a regular file cannot be created by anyone.
    const std::string file = tmp.Path() + "/regular";
    std::ofstream(file) << "x";
    const std::string bad = file + "/x";
    DML dml;
    dml.Config(OutOfCore(bad));
    try
    {
      dml.OpenBlock(4, 10);
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      ExpectMentions(e, bad, ENOTDIR);
    }
  }
  {
    // A read-only bind mount, if this environment allows mounting.
    const std::string ro = tmp.Path() + "/ro";
    ASSERT_EQ(::mkdir(ro.c_str(), 0700), 0);
    if (::mount(ro.c_str(), ro.c_str(), nullptr, MS_BIND, nullptr) == 0)
    {
      if (::mount(nullptr, ro.c_str(), nullptr, MS_BIND | MS_REMOUNT | MS_RDONLY, nullptr) == 0)
      {
        DML dml;
        dml.Config(OutOfCore(ro));
        try
        {
          dml.OpenBlock(4, 10);
          ADD_FAILURE() << "no error";
        }
        catch (const StorageError& e)
        {
          ExpectMentions(e, ro, EROFS);
        }
      }
      ::umount2(ro.c_str(), MNT_DETACH);
    }
  }
}

TEST(StorageFault, ShortTransfersAreRetriedAndEOFIsAnError)
{
  static int calls = 0;
  static bool interrupted = false;
  const auto trickle = [](int, void* buf, std::size_t n, off_t off) -> ssize_t {
    ++calls;
    if (!interrupted)
    {
      interrupted = true;
      errno = EINTR;
      return -1;
    }
    const std::size_t c = n < 3 ? n : 3;
    for (std::size_t i = 0; i < c; ++i)
    {
      static_cast<unsigned char*>(buf)[i] = static_cast<unsigned char>(off + i);
    }
    return static_cast<ssize_t>(c);
  };
  std::vector<unsigned char> buf(100);
  detail::TransferAll(-1, buf.data(), buf.size(), 1000, +trickle, "read");
  EXPECT_EQ(calls, 1 + 34);
  for (std::size_t i = 0; i < buf.size(); ++i)
  {
    ASSERT_EQ(buf[i], static_cast<unsigned char>(1000 + i));
  }
  const auto eof = [](int, void*, std::size_t, off_t) -> ssize_t { return 0; };
  try
  {
    detail::TransferAll(-1, buf.data(), buf.size(), 0, +eof, "read");
    ADD_FAILURE() << "no error";
  }
  catch (const StorageError& e)
  {
    EXPECT_EQ(e.OsError(), EIO);
    EXPECT_NE(std::string(e.what()).find("no progress"), std::string::npos);
  }
  const auto eio = [](int, void*, std::size_t, off_t) -> ssize_t {
    errno = EIO;
    return -1;
  };
  EXPECT_THROW(detail::TransferAll(-1, buf.data(), 5, 0, +eio, "write"), StorageError);
  // A real short file read through the POSIX backend.
  TempDir tmp;
  auto posix = FileBackend::CreatePosix();
  const int fd = posix->Create(tmp.Path() + "/f");
  posix->WriteAt(fd, buf.data(), 10, 0);
  try
  {
    posix->ReadAt(fd, buf.data(), 20, 0);
    ADD_FAILURE() << "no error";
  }
  catch (const StorageError& e)
  {
    EXPECT_EQ(e.OsError(), EIO);
  }
  posix->Close(fd);
  posix->Remove(tmp.Path() + "/f");
  EXPECT_THROW(posix->Create(tmp.Path() + "/missing/f"), StorageError);
}

TEST(StorageFault, CleanStaleDirectories)
{
  TempDir tmp;
  const pid_t child = ::fork();
  if (child == 0)
  {
    ::_exit(0);
  }
  ASSERT_GT(child, 0);
  ::waitpid(child, nullptr, 0); // now a dead pid
  const std::string dead = tmp.Path() + "/sipmss-" + std::to_string(child) + "-0123abcd0";
  const std::string live = tmp.Path() + "/sipmss-" + std::to_string(::getpid()) + "-4567ef010";
  const std::string other = tmp.Path() + "/sipmss-notapid";
  for (const auto& d : { dead, live, other })
  {
    ASSERT_EQ(::mkdir(d.c_str(), 0700), 0);
    std::ofstream(d + "/3.blk") << "data";
  }
  EXPECT_EQ(DML::CleanStaleDirectories(tmp.Path()), 1);
  EXPECT_NE(::access(dead.c_str(), F_OK), 0);
  EXPECT_EQ(::access(live.c_str(), F_OK), 0);
  EXPECT_EQ(::access(other.c_str(), F_OK), 0);
  EXPECT_THROW(DML::CleanStaleDirectories(tmp.Path() + "/missing"), StorageError);
}

TEST(StorageFault, ChildProcessGetsItsOwnDirectory)
{
  TempDir tmp;
  DML parent;
  parent.Config(OutOfCore(tmp.Path()));
  Array<int> a(parent, 1000);
  int fds[2];
  ASSERT_EQ(::pipe(fds), 0);
  const pid_t child = ::fork();
  if (child == 0)
  {
    int status = 1;
    try
    {
      DML dml;
      dml.Config(OutOfCore(tmp.Path()));
      Array<int> b(dml, 1000);
      b.Set(5, 5);
      const std::string d = dml.PrivateDirectory();
      status = d != parent.PrivateDirectory() && b.Get(5) == 5 ? 0 : 2;
    }
    catch (...)
    {
      status = 3;
    }
    (void)!::write(fds[1], &status, sizeof(status));
    ::_exit(0);
  }
  int status = -1;
  ASSERT_EQ(::read(fds[0], &status, sizeof(status)), static_cast<ssize_t>(sizeof(status)));
  ::waitpid(child, nullptr, 0);
  ::close(fds[0]);
  ::close(fds[1]);
  EXPECT_EQ(status, 0);
  EXPECT_EQ(ListDir(tmp.Path()).size(), 1u); // the child cleaned up after itself
}

} // namespace

// Issue 20 items 12 and 13: several temporary directories fall back when one cannot be used or
// has no room, and say so; the block files' size is counted.
TEST(StorageFault, SeveralDirectoriesFallBackAndSaySo)
{
  TempDir tmp;
  const std::string good = tmp.Path() + "/good", missing = tmp.Path() + "/missing";
  ASSERT_EQ(::mkdir(good.c_str(), 0700), 0);
  {
    Profile p = OutOfCore(missing);
    p.directories.push_back(good);
    DML dml;
    dml.Config(p);
    Array<std::uint32_t> a(dml, 1000);
    a.Set(999, 5);
    EXPECT_EQ(a.Get(999), 5u);
    const std::vector<std::string> notes = dml.GetStats().notes;
    ASSERT_EQ(notes.size(), 1u);
    EXPECT_NE(notes[0].find(missing + ": No such file or directory"), std::string::npos) << notes[0];
    EXPECT_NE(notes[0].find("block files go to " + good), std::string::npos) << notes[0];
    EXPECT_EQ(ListDir(good).size(), 1u); // its private directory
  }
  EXPECT_TRUE(ListDir(good).empty());

  const std::string mnt = tmp.Path() + "/mnt";
  ASSERT_EQ(::mkdir(mnt.c_str(), 0700), 0);
  if (::mount("tmpfs", mnt.c_str(), "tmpfs", 0, "size=1m") != 0)
  {
    GTEST_SKIP() << "cannot mount a 1 MiB tmpfs here: " << std::strerror(errno);
  }
  {
    // No room for an 8 MiB block on the 1 MiB file system: it goes to the next directory.
    Profile p = OutOfCore(mnt);
    p.directories.push_back(good);
    DML dml;
    dml.Config(p);
    Array<std::uint64_t> a(dml, 1 << 20);
    const std::vector<std::uint64_t> data(a.Size(), 3);
    a.Write(0, data.size(), data.data());
    EXPECT_EQ(a.Get(12345), 3u);
    const Stats s = dml.GetStats();
    ASSERT_EQ(s.notes.size(), 1u);
    EXPECT_NE(s.notes[0].find(mnt + ": 1.0 MiB free"), std::string::npos) << s.notes[0];
    EXPECT_EQ(s.fileBytes, 8u << 20);
    EXPECT_EQ(s.peakFileBytes, 8u << 20);
  }
  {
    // Room when the block is opened, taken by another process before it is written: the file
    // moves to the next directory with its data, and the write is made there.
    Profile p = OutOfCore(mnt);
    p.directories.push_back(good);
    DML dml;
    dml.Config(p);
    Array<std::uint64_t> a(dml, 64 * 1024); // 512 KiB, on the tmpfs
    std::vector<std::uint64_t> data(a.Size());
    for (std::size_t i = 0; i < data.size(); ++i)
    {
      data[i] = i * 7 + 1;
    }
    a.Write(0, data.size() / 2, data.data());
    {
      std::ofstream fill(mnt + "/other", std::ios::binary);
      fill << std::string(600 * 1024, 'x');
    }
    a.Write(data.size() / 2, data.size() - data.size() / 2, data.data() + data.size() / 2);
    std::vector<std::uint64_t> back(data.size());
    a.Read(0, back.size(), back.data());
    EXPECT_EQ(back, data);
    const Stats s = dml.GetStats();
    ASSERT_EQ(s.notes.size(), 1u);
    EXPECT_NE(s.notes[0].find(mnt + ": No space left on device: block files go to " + good),
      std::string::npos)
      << s.notes[0];
    // Nothing of ours is left on the full file system.
    std::vector<std::string> left = ListDir(mnt);
    left.erase(std::remove(left.begin(), left.end(), "other"), left.end());
    for (const std::string& d : left)
    {
      EXPECT_TRUE(ListDir(mnt + "/" + d).empty()) << d;
    }
    ::unlink((mnt + "/other").c_str());
  }
  {
    // Every directory full: one error naming each, before anything is written.
    const std::string mnt2 = tmp.Path() + "/mnt2";
    ASSERT_EQ(::mkdir(mnt2.c_str(), 0700), 0);
    ASSERT_EQ(::mount("tmpfs", mnt2.c_str(), "tmpfs", 0, "size=1m"), 0);
    Profile p = OutOfCore(mnt);
    p.directories.push_back(mnt2);
    DML dml;
    dml.Config(p);
    try
    {
      Array<std::uint64_t> a(dml, 1 << 20);
      ADD_FAILURE() << "no error";
    }
    catch (const StorageError& e)
    {
      const std::string what = e.what();
      EXPECT_NE(what.find(mnt + ": 1.0 MiB free, 8.0 MiB needed"), std::string::npos) << what;
      EXPECT_NE(what.find(mnt2 + ": 1.0 MiB free, 8.0 MiB needed"), std::string::npos) << what;
      EXPECT_EQ(e.OsError(), ENOSPC);
    }
    ::umount2(mnt2.c_str(), MNT_DETACH);
  }
  ::umount2(mnt.c_str(), MNT_DETACH);
}

TEST(StorageFault, BlockFileBytesAreCounted)
{
  TempDir tmp;
  DML dml;
  dml.Config(OutOfCore(tmp.Path()));
  {
    Array<std::uint32_t> a(dml, 1000);
    Array<std::uint64_t> b(dml, 500);
    EXPECT_EQ(dml.GetStats().fileBytes, 8000u);
    b.Resize(1000);
    EXPECT_EQ(dml.GetStats().fileBytes, 12000u);
    b.Resize(100);
    EXPECT_EQ(dml.GetStats().fileBytes, 4800u);
  }
  EXPECT_EQ(dml.GetStats().fileBytes, 0u);
  EXPECT_EQ(dml.GetStats().peakFileBytes, 12000u);
}
