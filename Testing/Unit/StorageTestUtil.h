// Helpers shared by the Storage*Test.cpp suites.
#pragma once

#include <dirent.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <stdexcept>
#include <string>
#include <vector>

namespace sipmss::storage::testing
{

inline void RemoveAll(const std::string& path)
{
  std::error_code ec;
  std::filesystem::remove_all(path, ec);
}

// Names in a directory (without . and ..); empty if it does not exist.
inline std::vector<std::string> ListDir(const std::string& path)
{
  std::vector<std::string> names;
  if (DIR* d = ::opendir(path.c_str()))
  {
    while (const dirent* e = ::readdir(d))
    {
      if (std::strcmp(e->d_name, ".") != 0 && std::strcmp(e->d_name, "..") != 0)
      {
        names.emplace_back(e->d_name);
      }
    }
    ::closedir(d);
  }
  return names;
}

// A fresh directory under $TMPDIR or /tmp, removed with everything in it at scope exit.
class TempDir
{
public:
  TempDir()
  {
    const char* t = std::getenv("TMPDIR");
    std::string tmpl = std::string(t && *t ? t : "/tmp") + "/sipmss-test-XXXXXX";
    std::vector<char> buf(tmpl.begin(), tmpl.end());
    buf.push_back('\0');
    if (!::mkdtemp(buf.data()))
    {
      throw std::runtime_error("mkdtemp failed");
    }
    this->path_ = buf.data();
  }
  ~TempDir() { RemoveAll(this->path_); }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& Path() const { return this->path_; }

private:
  std::string path_;
};

} // namespace sipmss::storage::testing
