// StorageError, the POSIX file backend and the handling of private directories.
#include "DMLImpl.h"

#include <atomic>
#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <ctime>
#include <dirent.h>
#include <fcntl.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

namespace sipmss::storage
{

namespace
{
std::string ComposeMessage(const std::string& message, const std::string& path, int osError)
{
  std::string s = message;
  if (!path.empty())
  {
    s += ": ";
    s += path;
  }
  if (osError != 0)
  {
    s += ": ";
    s += detail::ErrnoText(osError);
  }
  return s;
}
} // namespace

StorageError::StorageError(const std::string& message, std::string path, int osError)
  : std::runtime_error(ComposeMessage(message, path, osError))
  , path_(std::move(path))
  , osError_(osError)
{
}

const char* ToString(Mode m)
{
  return m == Mode::InCore ? "in-core" : "out-of-core";
}

namespace detail
{

std::string ErrnoText(int error)
{
  char buf[256];
  // GNU strerror_r returns a pointer that may or may not be buf.
  const char* text = strerror_r(error, buf, sizeof(buf));
  return text ? std::string(text) : std::string("errno ") + std::to_string(error);
}

std::string DefaultDirectory()
{
  const char* t = std::getenv("TMPDIR");
  return (t && *t) ? std::string(t) : std::string("/tmp");
}

void TransferAll(int fd, void* buf, std::size_t bytes, std::uint64_t offset, IoOp op,
  const char* what)
{
  auto* p = static_cast<unsigned char*>(buf);
  while (bytes > 0)
  {
    // Linux transfers at most 0x7ffff000 bytes per call; ask for less to stay portable.
    const std::size_t chunk = bytes < (std::size_t(1) << 30) ? bytes : (std::size_t(1) << 30);
    const ssize_t n = op(fd, p, chunk, static_cast<off_t>(offset));
    if (n < 0)
    {
      if (errno == EINTR)
      {
        continue;
      }
      throw StorageError(what, "", errno);
    }
    if (n == 0)
    {
      // End of file on a read, or a write that makes no progress: never return partial data.
      throw StorageError(std::string(what) + " made no progress (short transfer at offset " +
          std::to_string(offset) + ")",
        "", EIO);
    }
    p += n;
    bytes -= static_cast<std::size_t>(n);
    offset += static_cast<std::uint64_t>(n);
  }
}

namespace
{
ssize_t PosixRead(int fd, void* buf, std::size_t n, off_t off)
{
  return ::pread(fd, buf, n, off);
}
ssize_t PosixWrite(int fd, void* buf, std::size_t n, off_t off)
{
  return ::pwrite(fd, buf, n, off);
}

// Stateless: errors carry no path, the DML adds it (it knows which block a handle belongs to).
class PosixBackend final : public FileBackend
{
public:
  int Create(const std::string& path) override
  {
    const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
    if (fd < 0)
    {
      throw StorageError("cannot create block file", path, errno);
    }
    // The DML caches pages itself and reads one page where it misses: kernel readahead around
    // those reads only fills the OS cache with pages nobody asked for, zeroing the sparse parts
    // of the file (measured: 6% of a Lucy-size run at 8 MB). Advice only.
    (void)::posix_fadvise(fd, 0, 0, POSIX_FADV_RANDOM);
    return fd;
  }
  void Close(int handle) override { ::close(handle); }
  void Remove(const std::string& path) override
  {
    if (::unlink(path.c_str()) != 0 && errno != ENOENT)
    {
      throw StorageError("cannot remove block file", path, errno);
    }
  }
  void ReadAt(int handle, void* dst, std::size_t bytes, std::uint64_t offset) override
  {
    TransferAll(handle, dst, bytes, offset, &PosixRead, "read");
  }
  void WriteAt(int handle, const void* src, std::size_t bytes, std::uint64_t offset) override
  {
    TransferAll(handle, const_cast<void*>(src), bytes, offset, &PosixWrite, "write");
  }
  void Truncate(int handle, std::uint64_t bytes) override
  {
    while (::ftruncate(handle, static_cast<off_t>(bytes)) != 0)
    {
      if (errno != EINTR)
      {
        throw StorageError("cannot resize block file", "", errno);
      }
    }
  }
  std::uint64_t AllocatedBytes(int handle) override
  {
    struct stat st;
    return ::fstat(handle, &st) == 0 ? std::uint64_t(st.st_blocks) * 512 : 0;
  }
  std::uint64_t FreeBytes(const std::string& directory) override
  {
    struct statvfs v;
    if (::statvfs(directory.c_str(), &v) != 0)
    {
      return ~std::uint64_t(0);
    }
    return std::uint64_t(v.f_bavail) * std::uint64_t(v.f_frsize);
  }
};

std::uint64_t StringCost(const std::string& s)
{
  return s.capacity() > 15 ? HeapCost(s.capacity() + 1) : 0;
}
} // namespace

std::uint64_t ProfileHeapCost(const Profile& p)
{
  std::uint64_t c = p.structures.empty() ? 0 : HeapCost(p.structures.capacity() * sizeof(StructureSpec));
  for (const auto& s : p.structures)
  {
    c += StringCost(s.name);
  }
  c += p.directories.empty() ? 0 : HeapCost(p.directories.capacity() * sizeof(std::string));
  for (const auto& d : p.directories)
  {
    c += StringCost(d);
  }
  return c;
}

std::string MakePrivateDirectory(const std::string& parentIn)
{
  std::string parent = parentIn;
  while (parent.size() > 1 && parent.back() == '/')
  {
    parent.pop_back();
  }
  // Unique per instance: pid + random + a process-wide counter; mkdir fails if it exists, so
  // two instances (threads or processes) can never end up sharing a directory.
  static std::atomic<std::uint64_t> counter{ 0 };
  for (int attempt = 0; attempt < 64; ++attempt)
  {
    std::uint64_t r = 0;
    if (::getrandom(&r, sizeof(r), GRND_NONBLOCK) != static_cast<ssize_t>(sizeof(r)))
    {
      r = static_cast<std::uint64_t>(std::time(nullptr)) * 0x9E3779B97F4A7C15ull ^
        reinterpret_cast<std::uintptr_t>(&r);
    }
    char name[96];
    std::snprintf(name, sizeof(name), "/sipmss-%ld-%08x%llx", static_cast<long>(::getpid()),
      static_cast<unsigned>(r), static_cast<unsigned long long>(counter.fetch_add(1)));
    std::string path = parent + name;
    if (::mkdir(path.c_str(), 0700) == 0)
    {
      return path;
    }
    if (errno != EEXIST)
    {
      throw StorageError("cannot create private directory", path, errno);
    }
  }
  throw StorageError("cannot create a unique private directory", parent, EEXIST);
}

void RemoveTree(const std::string& path) noexcept
{
  try
  {
    std::error_code ec; // best effort on cleanup paths; symlinks are removed, not followed
    std::filesystem::remove_all(path, ec);
  }
  catch (...)
  {
    // std::bad_alloc while building a path: nothing more can be done here
  }
}

} // namespace detail

std::unique_ptr<FileBackend> FileBackend::CreatePosix()
{
  return std::make_unique<detail::PosixBackend>();
}

// A private directory is named sipmss-<pid>-<random>. It is stale when no process with that pid
// exists: kill(pid, 0) fails with ESRCH (EPERM means the process exists but belongs to another
// user, so it is kept). Caveat: pids are only meaningful on this host and in this pid namespace;
// do not point this at a directory shared with other hosts or containers.
int DML::CleanStaleDirectories(const std::string& directory)
{
  DIR* d = ::opendir(directory.c_str());
  if (!d)
  {
    throw StorageError("cannot open directory", directory, errno);
  }
  std::vector<std::string> stale;
  while (const dirent* e = ::readdir(d))
  {
    const char* name = e->d_name;
    if (std::strncmp(name, "sipmss-", 7) != 0)
    {
      continue;
    }
    char* end = nullptr;
    errno = 0;
    const long pid = std::strtol(name + 7, &end, 10);
    if (errno != 0 || end == name + 7 || *end != '-' || pid <= 0)
    {
      continue;
    }
    if (::kill(static_cast<pid_t>(pid), 0) != 0 && errno == ESRCH)
    {
      stale.push_back(directory + "/" + name);
    }
  }
  ::closedir(d);
  int removed = 0;
  for (const auto& p : stale)
  {
    struct stat st{};
    if (::lstat(p.c_str(), &st) == 0 && S_ISDIR(st.st_mode))
    {
      detail::RemoveTree(p);
      removed += ::access(p.c_str(), F_OK) != 0 ? 1 : 0;
    }
  }
  return removed;
}

} // namespace sipmss::storage
