// The sipmss command-line tool: exit codes, error messages, no partial output, stats JSON.
#include "Sanitizers.h"

#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>
#include <zlib.h>

namespace fs = std::filesystem;

// Built with AddressSanitizer (scripts/sanitize), the CLI's memory is the sanitizer's: its shadow
// memory and quarantine make a peak RSS or an address-space limit mean nothing, and those tests
// skip.
#define SKIP_UNDER_ADDRESS_SANITIZER()                                                             \
  if (SIPMSS_ADDRESS_SANITIZER)                                                                    \
  {                                                                                                \
    GTEST_SKIP() << "memory is measured, and AddressSanitizer's own is in the way";                \
  }

namespace
{
struct Result
{
  int status = -1;
  std::string out;
};

// Runs a shell command line; its stdout and stderr together, and its exit status.
Result RunCommand(const std::string& commandLine)
{
  Result r;
  const std::string cmd = commandLine + " 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  std::array<char, 4096> buf{};
  std::size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0)
  {
    r.out.append(buf.data(), n);
  }
  const int st = ::pclose(p);
  r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
  return r;
}

Result RunCli(const std::string& args)
{
  return RunCommand(std::string(SIPMSS_CLI) + " " + args);
}

class CLI : public ::testing::Test
{
protected:
  void SetUp() override
  {
    this->dir = fs::temp_directory_path() /
      ("sipmss-cli-test-" + std::to_string(::getpid()) + "-" +
        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(this->dir);
    // a small closed mesh: an octahedron in ASCII PLY
    std::ofstream f(this->dir / "octa.ply");
    f << "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n"
         "property float z\nelement face 8\nproperty list uchar int vertex_indices\nend_header\n"
         "1 0 0\n-1 0 0\n0 1 0\n0 -1 0\n0 0 1\n0 0 -1\n"
         "3 0 2 4\n3 2 1 4\n3 1 3 4\n3 3 0 4\n3 2 0 5\n3 1 2 5\n3 3 1 5\n3 0 3 5\n";
  }
  void TearDown() override { fs::remove_all(this->dir); }
  std::string P(const std::string& name) const { return (this->dir / name).string(); }
  fs::path dir;
};
} // namespace

TEST_F(CLI, VersionAndUsage)
{
  Result v = RunCli("--version");
  EXPECT_EQ(v.status, 0);
  EXPECT_NE(v.out.find("sipmss"), std::string::npos);
  EXPECT_EQ(RunCli("").status, 2);
  EXPECT_EQ(RunCli("simplify only-one-arg").status, 2);
  EXPECT_EQ(RunCli("simplify a.ply b.ply --algorithm nonsense").status, 2);
  EXPECT_EQ(RunCli("simplify a.ply b.ply --grid 0").status, 2);
  EXPECT_EQ(RunCli("simplify a.ply b.ply --threads -1").status, 2);
}

TEST_F(CLI, InfoAndSimplify)
{
  Result info = RunCli("info " + P("octa.ply"));
  ASSERT_EQ(info.status, 0) << info.out;
  EXPECT_NE(info.out.find("\"vertices\": 6"), std::string::npos) << info.out;
  EXPECT_NE(info.out.find("\"faces\": 8"), std::string::npos) << info.out;

  Result s = RunCli("simplify " + P("octa.ply") + " " + P("out.ply") + " --grid 2 --quiet --stats-json " +
    P("stats.json"));
  ASSERT_EQ(s.status, 0) << s.out;
  EXPECT_TRUE(fs::exists(this->dir / "out.ply"));
  std::ifstream js(this->dir / "stats.json");
  std::string json((std::istreambuf_iterator<char>(js)), std::istreambuf_iterator<char>());
  EXPECT_NE(json.find("\"phases\""), std::string::npos);
  EXPECT_NE(json.find("\"mode\": \"in-core\""), std::string::npos);
  EXPECT_NE(json.find("\"input_triangles\": 8"), std::string::npos);
  EXPECT_NE(json.find("\"misses\""), std::string::npos);

  // out of core at a tiny budget, on one thread: same output bytes
  Result o = RunCli("simplify " + P("octa.ply") + " " + P("out2.ply") +
    " --grid 2 --quiet --threads 1 --memory-mb 0.0625 --tmpdir " + this->dir.string());
  ASSERT_EQ(o.status, 0) << o.out;
  std::ifstream a(this->dir / "out.ply", std::ios::binary), b(this->dir / "out2.ply", std::ios::binary);
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(a), {}), std::string(std::istreambuf_iterator<char>(b), {}));
  // --tmpdir before the positionals, twice: one directory each, the positionals stay positionals
  Result t = RunCli("simplify --tmpdir " + this->dir.string() + " --tmpdir " + this->dir.string() +
    " " + P("octa.ply") + " " + P("out3.ply") + " --grid 2 --quiet --memory-mb 0.0625");
  ASSERT_EQ(t.status, 0) << t.out;
  std::ifstream c3(this->dir / "out3.ply", std::ios::binary), a2(this->dir / "out.ply", std::ios::binary);
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(a2), {}), std::string(std::istreambuf_iterator<char>(c3), {}));

  Result c = RunCli("compare " + P("octa.ply") + " " + P("octa.ply") + " --samples 2000");
  ASSERT_EQ(c.status, 0) << c.out;
  const std::size_t h = c.out.find("\"hausdorff\": ");
  ASSERT_NE(h, std::string::npos) << c.out;
  EXPECT_LT(std::stod(c.out.substr(h + 13)), 1e-9) << c.out;
}

TEST_F(CLI, BadInputLeavesNothing)
{
  {
    std::ofstream f(this->dir / "bad.ply");
    f << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n";
  }
  {
    std::ofstream keep(this->dir / "existing.ply");
    keep << "precious";
  }
  Result r = RunCli("simplify " + P("bad.ply") + " " + P("existing.ply") + " --quiet");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("sipmss: error:"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("bad.ply"), std::string::npos) << r.out;
  // the user's file is untouched and no temporary file is left
  std::ifstream keep(this->dir / "existing.ply");
  std::string content((std::istreambuf_iterator<char>(keep)), std::istreambuf_iterator<char>());
  EXPECT_EQ(content, "precious");
  for (const auto& e : fs::directory_iterator(this->dir))
  {
    const std::string name = e.path().filename().string();
    EXPECT_TRUE(name == "octa.ply" || name == "bad.ply" || name == "existing.ply") << name;
  }
  Result m = RunCli("simplify " + P("missing.ply") + " " + P("o.ply") + " --quiet");
  EXPECT_EQ(m.status, 1);
  EXPECT_NE(m.out.find("missing.ply"), std::string::npos) << m.out;
}

TEST_F(CLI, StaleTemporariesOfKilledRunsAreRemoved)
{
  // A run killed with SIGKILL leaves .sipmss-<pid>-OUTPUT; the next run to OUTPUT removes it
  // when no process has that pid, and touches nothing else.
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0)
  {
    ::_exit(0);
  }
  int st = 0;
  ASSERT_EQ(::waitpid(child, &st, 0), child);
  const std::string dead = std::to_string(child);
  auto touch = [this](const std::string& name) { std::ofstream(this->dir / name) << "partial"; };
  touch(".sipmss-" + dead + "-out.ply");   // stale: removed
  touch(".sipmss-" + dead + "-other.ply"); // another output's: kept
  touch(".sipmss-1-out.ply");              // a live process's: kept
  touch(".sipmss-x" + dead + "-out.ply");  // not ours: kept
  fs::create_directory(this->dir / (".sipmss-" + dead + "0-out.ply")); // not a file: kept
  Result s = RunCli("simplify " + P("octa.ply") + " " + P("out.ply") + " --grid 2 --quiet");
  ASSERT_EQ(s.status, 0) << s.out;
  EXPECT_TRUE(fs::exists(this->dir / "out.ply"));
  EXPECT_FALSE(fs::exists(this->dir / (".sipmss-" + dead + "-out.ply")));
  EXPECT_TRUE(fs::exists(this->dir / (".sipmss-" + dead + "-other.ply")));
  EXPECT_TRUE(fs::exists(this->dir / ".sipmss-1-out.ply"));
  EXPECT_TRUE(fs::exists(this->dir / (".sipmss-x" + dead + "-out.ply")));
  EXPECT_TRUE(fs::is_directory(this->dir / (".sipmss-" + dead + "0-out.ply")));
}

TEST_F(CLI, InterruptCleansUp)
{
  // A mesh big enough that decimating it at a 4 MB budget on one thread takes a second or more.
  const int n = 700; // 2 * 700^2 = 980K triangles
  {
    std::ofstream f(this->dir / "big.ply", std::ios::binary);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex " << (n + 1) * (n + 1)
      << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << 2 * n * n
      << "\nproperty list uchar int vertex_indices\nend_header\n";
    for (int j = 0; j <= n; ++j)
      for (int i = 0; i <= n; ++i)
      {
        const float p[3] = { float(i), float(j), float(std::sin(i * 0.05) * std::cos(j * 0.07)) };
        f.write(reinterpret_cast<const char*>(p), sizeof(p));
      }
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i)
      {
        const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
        const int t[2][3] = { { a, b, c }, { a, c, d } };
        for (const auto& tri : t)
        {
          const unsigned char three = 3;
          f.write(reinterpret_cast<const char*>(&three), 1);
          f.write(reinterpret_cast<const char*>(tri), sizeof(tri));
        }
      }
  }
  // The interrupt comes 0.3 s after the run went out of core (its private directory exists), not
  // after a fixed delay from the start: on two threads the whole run takes under a second.
  const std::string cmd = "sh -c '" + std::string(SIPMSS_CLI) + " simplify " + P("big.ply") + " " +
    P("out.ply") + " --algorithm decimate --target 100 --memory-mb 4 --threads 1 --tmpdir " +
    this->dir.string() + " & p=$!; for i in $(seq 1000); do ls -d " + this->dir.string() +
    "/sipmss-* >/dev/null 2>&1 && break; sleep 0.01; done; sleep 0.3; kill -INT $p; wait $p; echo status=$?'";
  FILE* p = ::popen(cmd.c_str(), "r");
  std::string out;
  std::array<char, 256> buf{};
  std::size_t k;
  while ((k = std::fread(buf.data(), 1, buf.size(), p)) > 0)
  {
    out.append(buf.data(), k);
  }
  ::pclose(p);
  EXPECT_NE(out.find("status=130"), std::string::npos) << out;
  for (const auto& e : fs::directory_iterator(this->dir))
  {
    const std::string name = e.path().filename().string();
    EXPECT_TRUE(name == "octa.ply" || name == "big.ply") << "left behind: " << name;
  }
}

namespace
{
std::string ReadAll(const fs::path& p)
{
  std::ifstream f(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(f), {});
}

// A binary PLY of an n x n grid of quads (2 n^2 triangles) with a bumpy height, its vertices in
// scanner order; with a `stride` coprime with the vertex count, vertex v is numbered
// v * stride mod V instead (a permutation that puts neighbours far apart in index order).
void WriteGrid(const std::string& path, int n, std::uint32_t stride = 1)
{
  const std::uint32_t V = std::uint32_t(n + 1) * std::uint32_t(n + 1);
  auto image = [V, stride](std::uint32_t v) {
    return std::uint32_t((std::uint64_t(v) * stride) % V);
  };
  std::ofstream f(path, std::ios::binary);
  f << "ply\nformat binary_little_endian 1.0\nelement vertex " << V
    << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << 2 * n * n
    << "\nproperty list uchar int vertex_indices\nend_header\n";
  std::vector<float> xyz(3 * std::size_t(V));
  for (int j = 0; j <= n; ++j)
  {
    for (int i = 0; i <= n; ++i)
    {
      float* q = &xyz[3 * std::size_t(image(std::uint32_t(j * (n + 1) + i)))];
      q[0] = float(i), q[1] = float(j), q[2] = float((i * j) % 7);
    }
  }
  f.write(reinterpret_cast<const char*>(xyz.data()), std::streamsize(xyz.size() * 4));
  std::vector<char> faces(13 * 2 * std::size_t(n));
  for (int j = 0; j < n; ++j)
  {
    char* p = faces.data();
    for (int i = 0; i < n; ++i)
    {
      const std::uint32_t a = std::uint32_t(j * (n + 1) + i), b = a + 1, c = a + n + 2,
                          d = a + n + 1;
      const std::uint32_t t[2][3] = { { image(a), image(b), image(c) },
        { image(a), image(c), image(d) } };
      for (const auto& tri : t)
      {
        *p++ = 3;
        std::memcpy(p, tri, 12);
        p += 12;
      }
    }
    f.write(faces.data(), std::streamsize(faces.size()));
  }
}
} // namespace

TEST_F(CLI, RefusesToOverwriteTheInput)
{
  // The input is never replaced: not by OUTPUT as given, through ./, a symlink or a hard link,
  // nor by a level of detail or the statistics file. Each is a usage error (exit 2) that names
  // the path, and the input keeps its bytes.
  const std::string before = ReadAll(this->dir / "octa.ply");
  fs::create_symlink(this->dir / "octa.ply", this->dir / "link.ply");
  fs::create_hard_link(this->dir / "octa.ply", this->dir / "hard.ply");
  fs::copy_file(this->dir / "octa.ply", this->dir / "scan_lod1.ply");
  const std::string lodBefore = ReadAll(this->dir / "scan_lod1.ply");
  const std::string cd = "cd " + this->dir.string() + " && " + SIPMSS_CLI;
  struct Case
  {
    std::string cmd, named;
  };
  const Case cases[] = {
    { std::string(SIPMSS_CLI) + " simplify " + P("octa.ply") + " " + P("octa.ply"), "octa.ply" },
    { cd + " simplify octa.ply ./octa.ply", "./octa.ply" },
    { cd + " simplify ./octa.ply " + P("octa.ply"), "octa.ply" },
    { std::string(SIPMSS_CLI) + " simplify " + P("octa.ply") + " " + P("link.ply"), "link.ply" },
    { std::string(SIPMSS_CLI) + " simplify " + P("link.ply") + " " + P("octa.ply"), "octa.ply" },
    { std::string(SIPMSS_CLI) + " simplify " + P("octa.ply") + " " + P("hard.ply"), "hard.ply" },
    { std::string(SIPMSS_CLI) + " simplify " + P("octa.ply") + " " + P("out.ply") + " --stats-json " +
        P("octa.ply"),
      "octa.ply" },
    { std::string(SIPMSS_CLI) + " simplify " + P("scan_lod1.ply") + " " + P("scan.ply") +
        " --algorithm decimate --lods 3",
      "scan_lod1.ply" },
  };
  for (const auto& c : cases)
  {
    for (const char* algorithm : { "", " --algorithm decimate", " --algorithm two-stage" })
    {
      const std::string cmd = c.cmd + (c.cmd.find("--algorithm") == std::string::npos ? algorithm : "") +
        " --quiet";
      const Result r = RunCommand(cmd);
      EXPECT_EQ(r.status, 2) << cmd << "\n" << r.out;
      EXPECT_NE(r.out.find("refusing to overwrite the input"), std::string::npos) << cmd << "\n" << r.out;
      EXPECT_NE(r.out.find(c.named), std::string::npos) << cmd << "\n" << r.out;
      EXPECT_EQ(ReadAll(this->dir / "octa.ply"), before) << cmd;
      EXPECT_EQ(ReadAll(this->dir / "scan_lod1.ply"), lodBefore) << cmd;
    }
  }
  EXPECT_TRUE(fs::is_symlink(this->dir / "link.ply"));
  EXPECT_FALSE(fs::exists(this->dir / "out.ply"));
  EXPECT_FALSE(fs::exists(this->dir / "scan.ply"));
  for (const auto& e : fs::directory_iterator(this->dir))
  {
    const std::string name = e.path().filename().string();
    EXPECT_NE(name.rfind(".sipmss-", 0), 0u) << "left behind: " << name;
  }
  // a different file with the same content is not the input
  fs::copy_file(this->dir / "octa.ply", this->dir / "copy.ply");
  Result ok = RunCli("simplify " + P("octa.ply") + " " + P("copy.ply") + " --grid 2 --quiet");
  EXPECT_EQ(ok.status, 0) << ok.out;
  EXPECT_EQ(ReadAll(this->dir / "octa.ply"), before);
}

TEST_F(CLI, OutputIsCheckedBeforeTheRun)
{
  // A big input whose read alone takes seconds: every output problem must be reported at once,
  // naming the user's path (not a temporary name), with nothing written.
  const std::string big = P("big.ply");
  WriteGrid(big, 1500); // 4.5M triangles, 54 MB
  fs::create_directory(this->dir / "adir.ply");
  struct Case
  {
    std::string output, extra, says;
  };
  const Case cases[] = {
    { P("out.vtp"), "", "out.vtp: unknown mesh file extension '.vtp'" },
    { P("out"), "", "out: no mesh file extension" },
    { P("out.gz"), "", "out.gz: no mesh file extension" },
    { P("missing/out.ply"), "", "missing/out.ply: cannot write the output: the directory" },
    { P("adir.ply"), "", "adir.ply: cannot write the output: it is a directory" },
    { P("out.ply"), " --stats-json " + P("missing/s.json"),
      "missing/s.json: cannot write the statistics: the directory" },
    { P("out.ply"), " --algorithm decimate --lods 2 --stats-json " + P("adir.ply/x/s.json"),
      "adir.ply/x/s.json: cannot write the statistics" },
  };
  for (const auto& c : cases)
  {
    const auto start = std::chrono::steady_clock::now();
    Result r = RunCli("simplify " + big + " " + c.output + c.extra + " --quiet");
    const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    EXPECT_EQ(r.status, 1) << c.output << c.extra << "\n" << r.out;
    EXPECT_NE(r.out.find(c.says), std::string::npos) << r.out;
    EXPECT_EQ(r.out.find(".sipmss-"), std::string::npos) << "names a temporary: " << r.out;
    EXPECT_LT(seconds, 1.0) << c.output << c.extra; // the read alone takes longer
  }
  // A 25M-triangle input (a sparse file: its header announces 12.5M vertices and 25M faces; no
  // disk is used): the extension is refused at once, before any of it is read.
  {
    const std::uint64_t nv = 12500000, nf = 25000000;
    std::ofstream f(P("huge.ply"), std::ios::binary);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex " << nv
      << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << nf
      << "\nproperty list uchar int vertex_indices\nend_header\n";
    const std::uint64_t size = std::uint64_t(f.tellp()) + 12 * nv + 13 * nf;
    f.close();
    fs::resize_file(P("huge.ply"), size);
    const auto start = std::chrono::steady_clock::now();
    Result r = RunCli("simplify " + P("huge.ply") + " " + P("out.vtp") + " --algorithm decimate --quiet");
    const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    EXPECT_EQ(r.status, 1) << r.out;
    EXPECT_NE(r.out.find("out.vtp: unknown mesh file extension '.vtp'"), std::string::npos) << r.out;
    EXPECT_LT(seconds, 1.0);
    fs::remove(P("huge.ply"));
  }
  for (const auto& e : fs::directory_iterator(this->dir))
  {
    const std::string name = e.path().filename().string();
    EXPECT_TRUE(name == "octa.ply" || name == "big.ply" || name == "adir.ply") << name;
  }
}

TEST_F(CLI, CompressedOutputs)
{
  for (const char* ext : { ".ply.gz", ".stl.gz", ".obj.gz", ".PLY.GZ" })
  {
    const std::string out = P(std::string("out") + ext);
    Result r = RunCli("simplify " + P("octa.ply") + " " + out + " --algorithm decimate --target 4 --quiet");
    ASSERT_EQ(r.status, 0) << ext << "\n" << r.out;
    const std::string bytes = ReadAll(out);
    ASSERT_GE(bytes.size(), 2u);
    EXPECT_EQ(static_cast<unsigned char>(bytes[0]), 0x1f) << ext; // gzip magic
    EXPECT_EQ(static_cast<unsigned char>(bytes[1]), 0x8b) << ext;
    Result info = RunCli("info " + out);
    ASSERT_EQ(info.status, 0) << info.out;
    EXPECT_NE(info.out.find("\"triangles\": 4"), std::string::npos) << ext << "\n" << info.out;
  }
  // the same bytes, compressed or not
  ASSERT_EQ(RunCli("simplify " + P("octa.ply") + " " + P("plain.ply") + " --algorithm decimate --target 4 --quiet").status, 0);
  gzFile gz = gzopen(P("out.ply.gz").c_str(), "rb");
  ASSERT_NE(gz, nullptr);
  std::string unzipped(1 << 16, '\0');
  const int n = gzread(gz, unzipped.data(), unsigned(unzipped.size()));
  gzclose(gz);
  ASSERT_GT(n, 0);
  unzipped.resize(std::size_t(n));
  EXPECT_EQ(unzipped, ReadAll(this->dir / "plain.ply"));
}

TEST_F(CLI, MeaninglessArgumentsAreUsageErrors)
{
  const std::string io = "simplify " + P("octa.ply") + " " + P("out.ply") + " --quiet ";
  const char* bad[] = {
    "--algorithm decimate --target -5",
    "--algorithm decimate --target 0",
    "--algorithm decimate --target -1",
    "--algorithm decimate --target 1e3x",
    "--target 100",                              // cluster has no target
    "--algorithm cluster --reduction 0.5",
    "--algorithm cluster --lods 2",
    "--algorithm decimate --grid 100",           // decimate has no grid
    "--algorithm cluster --max-error 1",         // the options of decimation only
    "--prune-size 0.1",
    "--algorithm decimate --prune-size 2",
    "--algorithm decimate --prune-size nan",
    "--algorithm cluster --lock-boundary",
    "--algorithm cluster --no-fit",
    "--algorithm cluster --weld 0.1",
    "--lock-array s",                            // locks and selections: decimation only
    "--algorithm two-stage --selection-array s",
    "--algorithm decimate --bounds 0 1 0 1 0 1", // the clustering's box
    "--algorithm two-stage --bounds 0 1 0 1 0 1",
    "--algorithm decimate --max-error nan",
    "--algorithm decimate --max-error -1",
    "--algorithm decimate --weld nan",
    "--algorithm decimate --weld inf",
    "--bounds 0 1 0 1 0 inf",
    "--bounds 0 1 0 1 0",
    "--mode sideways",
    "--threads 257",
    "--threads -1",
    "--algorithm decimate --lods 65",
    "--algorithm decimate --lods 0",
    "--grid 65536",
    "--boundary-weight -1",
    "--algorithm decimate --reduction nan",
    "--algorithm decimate --reduction inf",
    "--boundary-weight nan",
    "--memory-mb nan",
    "--memory-mb inf",
    "--memory-mb -2",
    "--memory-mb -0.5",
    "--memory-mb automatic-ish",
    "--memory-mb 1e-7",
    "--memory-mb 0.01",
    "--grid -3",
  };
  for (const char* args : bad)
  {
    Result r = RunCli(io + args);
    EXPECT_EQ(r.status, 2) << args << "\n" << r.out;
    EXPECT_FALSE(fs::exists(this->dir / "out.ply")) << args;
  }
  Result applies = RunCli(io + "--target 100");
  EXPECT_NE(applies.out.find("does not apply to --algorithm cluster"), std::string::npos) << applies.out;
  // what is meaningful still runs
  const char* good[] = { "--algorithm decimate --target 1", "--algorithm two-stage --grid 10 --target 4",
    "--algorithm decimate --reduction 0", "--memory-mb 0", "--memory-mb 0.0625", "--boundary-weight 1",
    "--memory-mb auto", "--memory-mb unbounded", "--memory-mb -1",
    "--algorithm two-stage --boundary-weight 1 --target 4", // stage 2's boundary quadrics
    "--algorithm decimate --boundary-weight 0", "--algorithm decimate --max-error inf",
    "--algorithm decimate --max-error 0.5 --lock-boundary --weld 0",
    "--algorithm decimate --target 100 --no-fit",
    "--algorithm two-stage --grid 10 --lock-boundary --weld 0.01 --max-error 1",
    "--algorithm two-stage --grid 10 --prune-size 0.1 --target 4",
    "--algorithm decimate --prune-size 0 --target 4",
    "--bounds -2 2 -2 2 -2 2", "--mode in-core", "--mode out-of-core --memory-mb 1",
    "--algorithm decimate --mode out-of-core --memory-mb 1 --threads 2" };
  for (const char* args : good)
  {
    Result r = RunCli(io + args);
    EXPECT_EQ(r.status, 0) << args << "\n" << r.out;
  }
}

// The stats JSON lists the decimation's passes: each with its sizes, work, steps' seconds and
// I/O (out of core by array too); the last one ends at the output's triangle count; two-stage
// names its stage-2 passes; a clustering has none.
TEST_F(CLI, StatsListTheDecimationPasses)
{
  const std::string in = this->P("bumps.ply");
  WriteGrid(in, 24);
  const char* keys[] = { "\"vertices\"", "\"triangles\"", "\"goal\"", "\"triangles_after\"",
    "\"active_vertices\"", "\"edges_placed\"", "\"candidates\"", "\"collapses\"",
    "\"illegal\"", "\"steps\"", "\"sweep\"", "\"order\"", "\"step\"", "\"compact\"",
    "\"seconds\"", "\"bytes_read\"", "\"bytes_written\"", "\"misses\"", "\"mode\"",
    "\"arrays\"" };
  for (const char* algorithm : { "decimate", "two-stage" })
  {
    Result r = RunCli("simplify " + in + " " + this->P("out.ply") + " --quiet --target 100" +
      (std::string(algorithm) == "two-stage" ? " --grid 16" : "") + " --algorithm " + algorithm +
      " --stats-json " + this->P("s.json"));
    ASSERT_EQ(r.status, 0) << algorithm << "\n" << r.out;
    const std::string j = ReadAll(this->P("s.json"));
    const std::size_t at = j.find("\"passes\": [");
    ASSERT_NE(at, std::string::npos) << j;
    // (the keys come in alphabetical order: "peak_rss_mb" follows "passes")
    const std::size_t end = j.find("\"peak_rss_mb\"", at);
    ASSERT_NE(end, std::string::npos) << j;
    const std::string passes = j.substr(at, end - at);
    for (const char* k : keys)
    {
      EXPECT_NE(passes.find(k), std::string::npos) << algorithm << " " << k << "\n" << j;
    }
    EXPECT_EQ(passes.find("\"run\": \"stage 2 \"") != std::string::npos,
      std::string(algorithm) == "two-stage") << j;
    // The last pass ends at the output's count.
    const std::size_t out = j.find("\"output_triangles\": ");
    ASSERT_NE(out, std::string::npos) << j;
    const std::string count = j.substr(out + 20, j.find_first_of(",\n", out + 20) - out - 20);
    const std::size_t last = passes.rfind("\"triangles_after\": ");
    ASSERT_NE(last, std::string::npos) << j;
    EXPECT_EQ(passes.substr(last + 19, count.size() + 1), count + ",") << j;
  }
  // Out of core, the steps' I/O by array too (in core none: "arrays": []).
  EXPECT_NE(ReadAll(this->P("s.json")).find("\"arrays\": []"), std::string::npos);
  const std::string big = this->P("big.ply");
  WriteGrid(big, 100); // (20,000 triangles: more than 0.25 MB of blocks)
  Result o = RunCli("simplify " + big + " " + this->P("out.ply") +
    " --quiet --target 100 --algorithm decimate --memory-mb 0.25 --stats-json " +
    this->P("o.json"));
  ASSERT_EQ(o.status, 0) << o.out;
  const std::string oj = ReadAll(this->P("o.json"));
  for (const char* a :
    { "\"name\": \"positions\"", "\"name\": \"quadrics\"", "\"name\": \"faces\"" })
  {
    EXPECT_NE(oj.find(a), std::string::npos) << a << "\n" << oj;
  }
  Result c = RunCli("simplify " + in + " " + this->P("c.ply") + " --quiet --grid 8 --stats-json " +
    this->P("c.json"));
  ASSERT_EQ(c.status, 0) << c.out;
  EXPECT_NE(ReadAll(this->P("c.json")).find("\"passes\": []"), std::string::npos);
}

// The stats JSON lists the layout step's parts when the input was reordered: a grid whose
// vertices are numbered by a fixed permutation (neighbours far apart in index order), out of
// core; none for the grid in scanner order.
TEST_F(CLI, StatsListTheLayoutStepsParts)
{
  const int n = 200; // (40,401 vertices: jumps beyond the layout probe's window of 4,096)
  const std::uint32_t V = std::uint32_t(n + 1) * std::uint32_t(n + 1);
  const std::uint32_t stride = 2654435761u % V; // (coprime with V: a permutation)
  ASSERT_EQ(std::gcd(stride, V), 1u);
  const std::string shuffled = this->P("shuffled.ply");
  WriteGrid(shuffled, n, stride);
  const std::string ordered = this->P("ordered.ply");
  WriteGrid(ordered, n);
  for (const bool isShuffled : { true, false })
  {
    Result r = RunCli("simplify " + (isShuffled ? shuffled : ordered) + " " + this->P("o.ply") +
      " --quiet --algorithm decimate --target 500 --memory-mb 1 --stats-json " + this->P("s.json"));
    ASSERT_EQ(r.status, 0) << r.out;
    const std::string j = ReadAll(this->P("s.json"));
    EXPECT_NE(j.find(std::string("\"reordered\": ") + (isShuffled ? "true" : "false")),
      std::string::npos) << j;
    const std::size_t at = j.find("\"layout_steps\": [");
    ASSERT_NE(at, std::string::npos) << j;
    const std::string steps = j.substr(at, j.find(']', at) - at);
    const char* names[] = { "vertices by key", "inverse", "faces renumbered", "faces sorted" };
    std::size_t from = 0;
    for (const char* name : names)
    {
      const std::size_t k = steps.find(std::string("\"name\": \"") + name + "\"", from);
      EXPECT_EQ(k != std::string::npos, isShuffled) << name << "\n" << j;
      from = k == std::string::npos ? from : k; // (in this order)
    }
    for (const char* key : { "\"seconds\"", "\"bytes_read\"", "\"bytes_written\"", "\"file_bytes\"" })
    {
      EXPECT_EQ(steps.find(key) != std::string::npos, isShuffled) << key << "\n" << j;
    }
  }
}

// Two-stage without --grid: with --target T the grid whose clustered mesh has about 16 T
// triangles, max(300, ceil(sqrt(16 T / 3.4))), without --target 300; the grid run is in the
// statistics ("grid") and the summary line. A grid finer than 300 whose clustered mesh would
// keep at least 0.7 of the input's triangles (3.4 g^2 of them) skips stage 1: the decimation
// alone, byte for byte, "grid" null. A given grid always runs stage 1.
TEST_F(CLI, TwoStageGridFollowsTheTarget)
{
  const std::string in = this->P("bumps.ply");
  const double faces = 2.0 * 500 * 500;
  WriteGrid(in, 500);
  auto number = [](const std::string& json, const std::string& key) {
    const std::size_t k = json.find("\"" + key + "\": ");
    EXPECT_NE(k, std::string::npos) << key << "\n" << json;
    return k == std::string::npos ? -1.0 : std::stod(json.substr(k + key.size() + 4));
  };
  for (const int target : { 1000, 20000, 40000 })
  {
    Result r = RunCli("simplify " + in + " " + this->P("out.ply") + " --algorithm two-stage --target " +
      std::to_string(target) + " --stats-json " + this->P("s.json"));
    ASSERT_EQ(r.status, 0) << r.out;
    const int grid = std::max(300, int(std::ceil(std::sqrt(16.0 * target / 3.4))));
    EXPECT_EQ(grid, target == 1000 ? 300 : target == 20000 ? 307 : 434);
    const bool skipped = grid > 300 && 3.4 * grid * grid >= 0.7 * faces;
    EXPECT_EQ(skipped, target == 40000);
    const std::string j = ReadAll(this->P("s.json"));
    EXPECT_LE(number(j, "output_triangles"), target);
    EXPECT_GE(number(j, "output_triangles"), target - 2);
    if (!skipped)
    {
      EXPECT_EQ(number(j, "grid"), grid) << j;
      EXPECT_NE(r.out.find("two-stage (grid " + std::to_string(grid) + ")"), std::string::npos)
        << r.out;
      continue;
    }
    EXPECT_NE(j.find("\"grid\": null"), std::string::npos) << j;
    EXPECT_NE(r.out.find("two-stage (stage 1 skipped"), std::string::npos) << r.out;
    Result d = RunCli("simplify " + in + " " + this->P("alone.ply") +
      " --algorithm decimate --quiet --target " + std::to_string(target));
    ASSERT_EQ(d.status, 0) << d.out;
    EXPECT_EQ(ReadAll(this->P("out.ply")), ReadAll(this->P("alone.ply")));
    // The same grid given: stage 1 runs.
    r = RunCli("simplify " + in + " " + this->P("out.ply") + " --algorithm two-stage --grid " +
      std::to_string(grid) + " --target " + std::to_string(target) + " --stats-json " +
      this->P("s.json"));
    ASSERT_EQ(r.status, 0) << r.out;
    EXPECT_EQ(number(ReadAll(this->P("s.json")), "grid"), grid);
  }
  Result r = RunCli("simplify " + in + " " + this->P("out.ply") +
    " --algorithm two-stage --reduction 0.5 --stats-json " + this->P("s.json"));
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_EQ(number(ReadAll(this->P("s.json")), "grid"), 300);
  r = RunCli("simplify " + in + " " + this->P("out.ply") + " --algorithm two-stage --grid 40 "
    "--target 100 --stats-json " + this->P("s.json"));
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_EQ(number(ReadAll(this->P("s.json")), "grid"), 40);
  r = RunCli("simplify " + in + " " + this->P("out.ply") + " --algorithm decimate --target 100 "
    "--stats-json " + this->P("s.json"));
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_NE(ReadAll(this->P("s.json")).find("\"grid\": null"), std::string::npos);
}

// --max-error is a fraction of the input's diagonal (or a distance with --absolute-error); the
// error reached is in the summary line and the statistics.
TEST_F(CLI, ErrorBoundAndAchievedError)
{
  const int n = 30;
  const std::string in = this->P("wavy.ply");
  {
    std::ofstream f(in);
    f << "ply\nformat ascii 1.0\nelement vertex " << (n + 1) * (n + 1)
      << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << 2 * n * n
      << "\nproperty list uchar int vertex_indices\nend_header\n";
    for (int j = 0; j <= n; ++j)
    {
      for (int i = 0; i <= n; ++i)
      {
        f << i << " " << j << " " << 3 * std::sin(0.3 * i) * std::cos(0.2 * j) << "\n";
      }
    }
    for (int j = 0; j < n; ++j)
    {
      for (int i = 0; i < n; ++i)
      {
        const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
        f << "3 " << a << " " << b << " " << c << "\n3 " << a << " " << c << " " << d << "\n";
      }
    }
  }
  auto number = [](const std::string& json, const std::string& key) {
    const std::size_t k = json.find("\"" + key + "\": ");
    EXPECT_NE(k, std::string::npos) << key << "\n" << json;
    return k == std::string::npos ? -1.0 : std::stod(json.substr(k + key.size() + 4));
  };
  Result r = RunCli("simplify " + in + " " + this->P("rel.ply") +
    " --algorithm decimate --max-error 0.002 --stats-json " + this->P("rel.json"));
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_NE(r.out.find(" of the diagonal)"), std::string::npos) << r.out;
  const std::string rel = ReadAll(this->P("rel.json"));
  const double achieved = number(rel, "achieved_error"), diagonal = number(rel, "diagonal");
  EXPECT_GT(achieved, 0.001) << rel; // (no target: as far as the bound allows)
  EXPECT_LE(achieved, 0.002 * (1 + 1e-6)) << rel;
  EXPECT_NEAR(diagonal, std::sqrt(2.0 * n * n + 36.0), 0.1) << rel;
  EXPECT_LT(number(rel, "output_triangles"), 0.5 * 2 * n * n) << rel;
  // The same bound as a distance: the same output.
  char absolute[64];
  std::snprintf(absolute, sizeof(absolute), "%.17g", 0.002 * diagonal);
  Result a = RunCli("simplify " + in + " " + this->P("abs.ply") +
    " --algorithm decimate --quiet --absolute-error --max-error " + absolute);
  ASSERT_EQ(a.status, 0) << a.out;
  EXPECT_EQ(ReadAll(this->P("rel.ply")), ReadAll(this->P("abs.ply")));
  // A cluster run reports its error too.
  Result c = RunCli("simplify " + in + " " + this->P("c.ply") + " --grid 8 --quiet --stats-json " +
    this->P("c.json"));
  ASSERT_EQ(c.status, 0) << c.out;
  EXPECT_GT(number(ReadAll(this->P("c.json")), "achieved_error"), 0.0);
  // Options that cannot mean anything are refused.
  for (const char* bad : { " --algorithm decimate --absolute-error",
         " --algorithm decimate --max-error 0.01 --reduction 0.5", " --absolute-error --max-error 1" })
  {
    Result b = RunCli("simplify " + in + " " + this->P("b.ply") + bad);
    EXPECT_EQ(b.status, 2) << bad << "\n" << b.out;
    EXPECT_FALSE(fs::exists(this->P("b.ply"))) << bad;
  }
  Result lods = RunCli("simplify " + in + " " + this->P("l.ply") +
    " --algorithm decimate --quiet --max-error 0.01 --target 100 --lods 3");
  EXPECT_EQ(lods.status, 0) << lods.out;
  // Levels of detail by the bound alone: level K stops at half of level K + 1's bound, so each
  // has fewer triangles than the one before; the last is OUTPUT.
  for (const char* algorithm : { "decimate", "two-stage --grid 20" })
  {
    Result b = RunCli("simplify " + in + " " + this->P("e.ply") + " --quiet --algorithm " +
      algorithm + " --max-error 0.004 --lods 3");
    ASSERT_EQ(b.status, 0) << algorithm << "\n" << b.out;
    double last = 2.0 * n * n + 1;
    for (int level = 0; level < 3; ++level)
    {
      const std::string path = this->P("e_lod" + std::to_string(level) + ".ply");
      Result info = RunCli("info " + path);
      ASSERT_EQ(info.status, 0) << info.out;
      const double triangles = number(info.out, "triangles");
      EXPECT_LT(triangles, last) << algorithm << " level " << level;
      last = triangles;
    }
    EXPECT_EQ(ReadAll(this->P("e.ply")), ReadAll(this->P("e_lod2.ply"))) << algorithm;
    // (two-stage at grid 20: the clustering's error, 0.0018 of the diagonal, is above the
    // finest level's bound, 0.001, and the user is told so)
    EXPECT_EQ(b.out.find("level of detail 0 (") != std::string::npos,
      std::string(algorithm) != "decimate")
      << algorithm << "\n" << b.out;
  }
  // A grid whose own error reaches the bound: the user is told that the output (or which
  // levels) stay at about the clustered mesh's size, on stderr and in the stats JSON.
  Result spent = RunCli("simplify " + in + " " + this->P("g.ply") +
    " --quiet --algorithm two-stage --grid 3 --max-error 0.0005 --stats-json " + this->P("g.json"));
  ASSERT_EQ(spent.status, 0) << spent.out;
  EXPECT_NE(spent.out.find("sipmss: warning: two-stage: the clustering's error"), std::string::npos)
    << spent.out;
  EXPECT_NE(spent.out.find("the output stays at about the clustered mesh's size"),
    std::string::npos) << spent.out;
  EXPECT_NE(ReadAll(this->P("g.json")).find("the output stays at about"), std::string::npos);
  Result levels = RunCli("simplify " + in + " " + this->P("h.ply") +
    " --quiet --algorithm two-stage --grid 3 --max-error 0.0005 --lods 2");
  ASSERT_EQ(levels.status, 0) << levels.out;
  EXPECT_NE(levels.out.find("every level of detail"), std::string::npos) << levels.out;
}

// --selection-array naming a face property: the same output from a gzip file whose face element
// comes first (its counts unknown until read) as from the plain file with the vertices first.
TEST_F(CLI, CellSelectionFromAFileWithTheFacesFirst)
{
  const int n = 16;
  auto write = [&](bool facesFirst) {
    std::ostringstream vertices, faces;
    for (int j = 0; j <= n; ++j)
    {
      for (int i = 0; i <= n; ++i)
      {
        vertices << i << " " << j << " " << (i * j) % 5 << "\n";
      }
    }
    for (int j = 0; j < n; ++j)
    {
      for (int i = 0; i < n; ++i)
      {
        const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
        const int sel = i < n / 2 ? 1 : 0;
        faces << "3 " << a << " " << b << " " << c << " " << sel << "\n3 " << a << " " << c << " "
              << d << " " << sel << "\n";
      }
    }
    const std::string ve = "element vertex " + std::to_string((n + 1) * (n + 1)) +
      "\nproperty float x\nproperty float y\nproperty float z\n";
    const std::string fe = "element face " + std::to_string(2 * n * n) +
      "\nproperty list uchar int vertex_indices\nproperty uchar sel\n";
    return "ply\nformat ascii 1.0\n" + (facesFirst ? fe + ve : ve + fe) + "end_header\n" +
      (facesFirst ? faces.str() + vertices.str() : vertices.str() + faces.str());
  };
  {
    std::ofstream f(this->P("plain.ply"));
    f << write(false);
  }
  const std::string gz = write(true);
  gzFile g = gzopen(this->P("first.ply.gz").c_str(), "wb");
  ASSERT_NE(g, nullptr);
  ASSERT_EQ(gzwrite(g, gz.data(), unsigned(gz.size())), int(gz.size()));
  gzclose(g);
  for (const char* in : { "plain.ply", "first.ply.gz" })
  {
    Result r = RunCli("simplify " + this->P(in) + " " + this->P(std::string(in) + ".out.ply") +
      " --algorithm decimate --target 60 --selection-array sel --quiet");
    ASSERT_EQ(r.status, 0) << in << "\n" << r.out;
  }
  const std::string a = ReadAll(this->P("plain.ply.out.ply")), b = ReadAll(this->P("first.ply.gz.out.ply"));
  EXPECT_EQ(a, b);
  // (half the faces are outside the selection and stay: far more than the target)
  EXPECT_GE(std::stoul(a.substr(a.find("element face ") + 13, 12)), std::size_t(n * n)) << a.substr(0, 300);
}

// --lock-array and --selection-array name a vertex property of the input: the locked vertices
// are in the output where they were; a name the input does not have is an error that names the
// file and the property, and writes nothing.
TEST_F(CLI, LockAndSelectionArraysNameAVertexProperty)
{
  const int n = 20;
  const std::string in = this->P("locks.ply");
  {
    std::ofstream f(in);
    f << "ply\nformat ascii 1.0\nelement vertex " << (n + 1) * (n + 1)
      << "\nproperty float x\nproperty float y\nproperty float z\nproperty uchar keep\n"
         "element face "
      << 2 * n * n << "\nproperty list uchar int vertex_indices\nend_header\n";
    for (int j = 0; j <= n; ++j)
    {
      for (int i = 0; i <= n; ++i)
      {
        f << i << " " << j << " " << (i * j) % 7 << " " << (i == j ? 1 : 0) << "\n";
      }
    }
    for (int j = 0; j < n; ++j)
    {
      for (int i = 0; i < n; ++i)
      {
        const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
        f << "3 " << a << " " << b << " " << c << "\n3 " << a << " " << c << " " << d << "\n";
      }
    }
  }
  const std::string out = this->P("locked.ply");
  Result r = RunCli("simplify " + in + " " + out +
    " --algorithm decimate --target 60 --lock-array keep --quiet");
  ASSERT_EQ(r.status, 0) << r.out;
  // The output: a binary PLY whose vertices are x y z keep, as floats.
  const std::string bytes = ReadAll(out);
  const std::size_t header = bytes.find("end_header\n");
  ASSERT_NE(header, std::string::npos);
  ASSERT_NE(bytes.find("property float keep\n"), std::string::npos) << bytes.substr(0, header);
  const std::size_t vertices =
    std::stoul(bytes.substr(bytes.find("element vertex ") + 15, 12));
  std::set<std::pair<int, int>> diagonal;
  for (std::size_t i = 0; i < vertices; ++i)
  {
    float v[4];
    std::memcpy(v, bytes.data() + header + 11 + 16 * i, 16);
    if (v[3] != 0)
    {
      EXPECT_EQ(v[0], v[1]) << "vertex " << i;
      EXPECT_EQ(v[2], float((int(v[0]) * int(v[1])) % 7)) << "vertex " << i;
      diagonal.insert({ int(v[0]), int(v[1]) });
    }
  }
  EXPECT_EQ(diagonal.size(), std::size_t(n + 1)) << "every locked vertex is in the output";
  Result missing = RunCli("simplify " + in + " " + this->P("m.ply") +
    " --algorithm decimate --lock-array kept --quiet");
  EXPECT_EQ(missing.status, 1) << missing.out;
  EXPECT_NE(missing.out.find("locks.ply"), std::string::npos) << missing.out;
  EXPECT_NE(missing.out.find("'kept'"), std::string::npos) << missing.out;
  EXPECT_NE(missing.out.find("keep"), std::string::npos) << missing.out;
  EXPECT_FALSE(fs::exists(this->P("m.ply")));
  Result selected = RunCli("simplify " + in + " " + this->P("s.ply") +
    " --algorithm decimate --target 60 --selection-array keep --quiet");
  EXPECT_EQ(selected.status, 0) << selected.out;
  // (only the diagonal is selected: at most its 21 vertices can go, so most faces stay)
  const std::string sel = ReadAll(this->P("s.ply"));
  EXPECT_GE(std::stoul(sel.substr(sel.find("element face ") + 13, 12)), std::size_t(2 * n * n - 80))
    << sel.substr(0, 300);
  Result weld = RunCli("simplify " + in + " " + this->P("w.ply") +
    " --algorithm decimate --lock-array keep --weld 0.1 --quiet");
  EXPECT_EQ(weld.status, 2) << weld.out;
  EXPECT_NE(weld.out.find("--weld"), std::string::npos) << weld.out;
  // `info` names what --lock-array and --selection-array can take
  Result info = RunCli("info " + in);
  EXPECT_EQ(info.status, 0) << info.out;
  EXPECT_NE(info.out.find("\"vertex_properties\": [\n    \"keep\"\n  ]"), std::string::npos)
    << info.out;
  EXPECT_NE(info.out.find("\"face_properties\": []"), std::string::npos) << info.out;
  const std::string faces = this->P("faces.ply");
  {
    std::ofstream f(faces);
    f << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         "property uchar sel\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2 1\n";
  }
  info = RunCli("info " + faces);
  EXPECT_EQ(info.status, 0) << info.out;
  EXPECT_NE(info.out.find("\"face_properties\": [\n    \"sel\"\n  ]"), std::string::npos)
    << info.out;
}

// --attributes weighs vertex properties in every algorithm; compare --attributes measures them.
// A name the input lacks is an error naming the file (nothing written); a bad list is a usage
// error.
TEST_F(CLI, AttributesJoinTheErrorAndCompareMeasuresThem)
{
  const int n = 24;
  const std::string in = this->P("colored.ply");
  {
    std::ofstream f(in);
    f << "ply\nformat ascii 1.0\nelement vertex " << (n + 1) * (n + 1)
      << "\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\n"
         "property uchar green\nproperty uchar blue\nproperty float h\nelement face "
      << 2 * n * n << "\nproperty list uchar int vertex_indices\nend_header\n";
    for (int j = 0; j <= n; ++j)
    {
      for (int i = 0; i <= n; ++i)
      {
        const bool left = 3 * i < n;
        f << i << " " << j << " " << (i * j) % 5 * 0.1 << " " << (left ? 250 : 10) << " 40 "
          << (left ? 10 : 200) << " " << 0.5 * i << "\n";
      }
    }
    for (int j = 0; j < n; ++j)
    {
      for (int i = 0; i < n; ++i)
      {
        const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
        f << "3 " << a << " " << b << " " << c << "\n3 " << a << " " << c << " " << d << "\n";
      }
    }
  }
  auto colorRms = [&](const std::string& out) {
    Result c = RunCli("compare " + in + " " + out + " --attributes colors,h --samples 20000");
    EXPECT_EQ(c.status, 0) << c.out;
    const std::size_t at = c.out.find("\"colors\"");
    EXPECT_NE(at, std::string::npos) << c.out;
    EXPECT_NE(c.out.find("\"h\""), std::string::npos) << c.out;
    const std::size_t rms = c.out.find("\"rms\": ", at);
    return std::stod(c.out.substr(rms + 7, 24));
  };
  for (const char* algorithm : { "decimate --target 100", "two-stage --grid 12 --target 100" })
  {
    Result plain = RunCli("simplify " + in + " " + this->P("plain.ply") + " --algorithm " +
      algorithm + " --quiet");
    ASSERT_EQ(plain.status, 0) << plain.out;
    Result aware = RunCli("simplify " + in + " " + this->P("aware.ply") + " --algorithm " +
      algorithm + " --attributes colors:1 --quiet");
    ASSERT_EQ(aware.status, 0) << aware.out;
    const double e0 = colorRms(this->P("plain.ply")), e1 = colorRms(this->P("aware.ply"));
    EXPECT_LT(e1, 0.7 * e0) << algorithm;
  }
  Result cluster = RunCli("simplify " + in + " " + this->P("c.ply") +
    " --algorithm cluster --grid 8 --attributes RGB:1,h:0.1 --quiet");
  EXPECT_EQ(cluster.status, 0) << cluster.out;
  Result missing = RunCli("simplify " + in + " " + this->P("m.ply") +
    " --algorithm decimate --attributes normals:1 --quiet");
  EXPECT_EQ(missing.status, 1) << missing.out;
  EXPECT_NE(missing.out.find("colored.ply"), std::string::npos) << missing.out;
  EXPECT_NE(missing.out.find("'normals'"), std::string::npos) << missing.out;
  EXPECT_NE(missing.out.find("colors (rgb, rgba), h"), std::string::npos) << missing.out;
  EXPECT_FALSE(fs::exists(this->P("m.ply")));
  Result bad = RunCli("simplify " + in + " " + this->P("b.ply") + " --attributes colors:0");
  EXPECT_EQ(bad.status, 2) << bad.out;
  EXPECT_NE(bad.out.find("--attributes"), std::string::npos) << bad.out;
  EXPECT_FALSE(fs::exists(this->P("b.ply")));
  // (compare measures the attributes as they are: weights are ignored)
  Result w1 = RunCli("compare " + in + " " + this->P("c.ply") + " --attributes colors --samples 5000");
  Result w3 = RunCli("compare " + in + " " + this->P("c.ply") + " --attributes colors:3 --samples 5000");
  EXPECT_EQ(w1.status, 0) << w1.out;
  EXPECT_EQ(w1.out, w3.out);
  Result noNormals = RunCli("compare " + in + " " + this->P("c.ply") + " --attributes normals");
  EXPECT_EQ(noNormals.status, 1) << noNormals.out;
  EXPECT_NE(noNormals.out.find("colored.ply"), std::string::npos) << noNormals.out;
  Result badList = RunCli("compare " + in + " " + this->P("c.ply") + " --attributes a,,b");
  EXPECT_EQ(badList.status, 2) << badList.out;
}

TEST_F(CLI, RepairsAreReported)
{
  // one good triangle, one face with two vertices and one with a repeated vertex
  {
    std::ofstream f(this->dir / "repair.ply");
    f << "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
         "property float z\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n1 0 0\n0 1 0\n1 1 0\n3 0 1 2\n2 1 3\n3 1 1 3\n";
  }
  for (const char* algorithm : { "cluster", "decimate", "two-stage" })
  {
    Result r = RunCli("simplify " + P("repair.ply") + " " + P("out.ply") + " --quiet --algorithm " +
      algorithm + " --stats-json " + P("s.json"));
    ASSERT_EQ(r.status, 0) << algorithm << "\n" << r.out;
    EXPECT_NE(r.out.find("repair.ply: dropped 2 degenerate faces"), std::string::npos) << r.out;
    EXPECT_NE(ReadAll(this->dir / "s.json").find("\"dropped_input_faces\": 2"), std::string::npos);
  }
  // nothing left to simplify: an error naming the file, nothing written
  {
    std::ofstream f(this->dir / "empty.ply");
    f << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n1 0 0\n0 1 0\n2 0 1\n";
  }
  for (const char* algorithm : { "cluster", "decimate", "two-stage" })
  {
    Result r = RunCli("simplify " + P("empty.ply") + " " + P("none.ply") + " --quiet --algorithm " + algorithm);
    EXPECT_EQ(r.status, 1) << algorithm << "\n" << r.out;
    EXPECT_NE(r.out.find("empty.ply: nothing to simplify"), std::string::npos) << algorithm << "\n" << r.out;
    EXPECT_FALSE(fs::exists(this->dir / "none.ply"));
  }
}

TEST_F(CLI, ProgressBarShowsPhasePercentElapsedAndTimeLeft)
{
  // On a terminal (script(1) gives the run a pseudo-terminal) the bar shows the phase, percent,
  // the elapsed time and, once a second has passed, an estimate of the time left.
  WriteGrid(P("grid.ply"), 900); // 1.6M triangles: more than a second at 4 MB on one thread
  const std::string cmd = "script -qec '" + std::string(SIPMSS_CLI) + " simplify " + P("grid.ply") +
    " " + P("out.ply") + " --algorithm decimate --target 1000 --memory-mb 4 --threads 1 --tmpdir " +
    this->dir.string() + "' /dev/null";
  const Result r = RunCommand(cmd);
  const std::string& out = r.out;
  ASSERT_EQ(r.status, 0) << out;
  EXPECT_NE(out.find("% collapse"), std::string::npos) << out.substr(0, 2000);
  EXPECT_NE(out.find(" elapsed"), std::string::npos) << out.substr(0, 2000);
  EXPECT_NE(out.find(" left"), std::string::npos) << out.substr(0, 2000);
  // percentages never go down
  int last = -1;
  for (std::size_t at = out.find("] "); at != std::string::npos; at = out.find("] ", at + 2))
  {
    const int percent = std::atoi(out.c_str() + at + 2);
    EXPECT_GE(percent, last) << out.substr(at > 200 ? at - 200 : 0, 400);
    last = percent;
  }
  EXPECT_GT(last, 50);
}

TEST_F(CLI, OutputsThatAreNotRegularFilesAreNeverReplaced)
{
  // A symlink as OUTPUT: the mesh goes to the link's target, the link stays a link.
  std::ofstream(this->dir / "real.ply") << "old";
  fs::create_symlink(this->dir / "real.ply", this->dir / "link.ply");
  Result r = RunCli("simplify " + P("octa.ply") + " " + P("link.ply") + " --grid 2 --quiet");
  ASSERT_EQ(r.status, 0) << r.out;
  EXPECT_TRUE(fs::is_symlink(this->dir / "link.ply"));
  EXPECT_EQ(ReadAll(this->dir / "real.ply").rfind("ply\n", 0), 0u);
  // A FIFO, a directory or a device is refused before the run and stays what it was.
  ASSERT_EQ(::mkfifo(P("fifo.ply").c_str(), 0600), 0);
  Result f = RunCli("simplify " + P("octa.ply") + " " + P("fifo.ply") + " --grid 2 --quiet");
  EXPECT_EQ(f.status, 1) << f.out;
  EXPECT_NE(f.out.find("fifo.ply: cannot write the output: it exists and is not a regular file"),
    std::string::npos) << f.out;
  EXPECT_TRUE(fs::is_fifo(this->dir / "fifo.ply"));
  Result s = RunCli("simplify " + P("octa.ply") + " " + P("o.ply") + " --grid 2 --quiet --stats-json /dev/null");
  EXPECT_EQ(s.status, 1) << s.out;
  EXPECT_NE(s.out.find("/dev/null: cannot write the statistics: it exists and is not a regular file"),
    std::string::npos) << s.out;
  EXPECT_FALSE(fs::exists(this->dir / "o.ply"));
}

TEST_F(CLI, StatisticsOnAFullDiskAreAnError)
{
  // A 16 KiB tmpfs, filled up: the statistics cannot be written, so the run fails (exit 1) and
  // writes nothing, neither the mesh nor a partial statistics file.
  const fs::path mnt = this->dir / "full";
  fs::create_directory(mnt);
  if (std::system(("mount -t tmpfs -o size=16k tmpfs " + mnt.string() + " 2>/dev/null").c_str()) != 0)
  {
    GTEST_SKIP() << "cannot mount a tmpfs here (needs root): skipping the full-disk test";
  }
  {
    std::ofstream fill(mnt / "fill", std::ios::binary);
    const std::string block(1024, 'x');
    for (int i = 0; i < 64 && fill; ++i)
    {
      fill << block << std::flush;
    }
  }
  Result r = RunCli("simplify " + P("octa.ply") + " " + P("out.ply") + " --grid 2 --quiet --stats-json " +
    (mnt / "s.json").string());
  const std::vector<std::string> left = [&] {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(mnt))
    {
      names.push_back(e.path().filename().string());
    }
    return names;
  }();
  EXPECT_EQ(std::system(("umount " + mnt.string()).c_str()), 0);
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find("s.json: cannot write the statistics: No space left on device"), std::string::npos)
    << r.out;
  EXPECT_FALSE(fs::exists(this->dir / "out.ply"));
  EXPECT_EQ(left, std::vector<std::string>{ "fill" });
}

// ---------------------------------------------------------------------------------------------
// Issue 20 items 4, 5, 9: aborts outside the cores, FIFO inputs, empty and degenerate inputs.
namespace
{
// Runs `sh -c SCRIPT` and returns its combined output.
std::string RunShell(const std::string& script)
{
  std::string quoted;
  for (char c : script)
  {
    quoted += c == '\'' ? std::string("'\\''") : std::string(1, c);
  }
  return RunCommand("sh -c '" + quoted + "'").out;
}

// Starts `sipmss ARGS` in the background, sends SIGINT after `delay` seconds, and prints
// "status=N seconds=S" (S: from the signal to the exit). A run that ignores the signal is killed
// after 8 s (status=137).
std::string InterruptAfter(const std::string& args, double delay)
{
  // --foreground: timeout forwards the SIGINT to the command only (without it, it also signals
  // its process group, and the command gets a second SIGINT, which kills it at once).
  return RunShell("timeout --foreground -s KILL 8 " + std::string(SIPMSS_CLI) + " " + args +
    " & p=$!; sleep " + std::to_string(delay) + "; t0=$(date +%s%N); kill -INT $p; wait $p; "
    "s=$?; t1=$(date +%s%N); echo status=$s seconds=$(( (t1 - t0) / 1000000 ))e-3");
}

double SecondsOf(const std::string& out)
{
  const auto at = out.find("seconds=");
  return at == std::string::npos ? 1e9 : std::atof(out.c_str() + at + 8);
}
} // namespace

TEST_F(CLI, InfoAndCompareStopOnTheFirstCtrlC)
{
  // compare with 1e11 samples runs for hours; info on a FIFO nobody writes to blocks forever.
  ASSERT_EQ(::mkfifo(P("silent.ply").c_str(), 0600), 0);
  const std::string runs[] = {
    "compare " + P("octa.ply") + " " + P("octa.ply") + " --samples 100000000000",
    "info " + P("silent.ply"),
  };
  for (const auto& args : runs)
  {
    const std::string out = InterruptAfter(args, 0.5);
    EXPECT_NE(out.find("status=130"), std::string::npos) << args << "\n" << out;
    EXPECT_NE(out.find("sipmss: interrupted; nothing was written"), std::string::npos) << out;
    EXPECT_LT(SecondsOf(out), 1.0) << args << "\n" << out;
  }
}

TEST_F(CLI, AFifoInputWorksAndCtrlCStopsAFifoWithoutWriter)
{
  WriteGrid(P("grid.ply"), 60);
  ASSERT_EQ(::mkfifo(P("in.ply").c_str(), 0600), 0);
  fs::create_directories(this->dir / "tmp");
  for (const std::string algorithm : { "cluster", "decimate", "two-stage" })
  {
    const std::string options = " --algorithm " + algorithm + " --quiet" +
      (algorithm == "cluster" ? " --grid 20" : " --target 500");
    Result ref = RunCli("simplify " + P("grid.ply") + " " + P("ref.ply") + options);
    ASSERT_EQ(ref.status, 0) << ref.out;
    // The cluster's bounds pass then its real read used to open the FIFO twice: a hang.
    const std::string out = RunShell("cat " + P("grid.ply") + " > " + P("in.ply") +
      " & TMPDIR=" + P("tmp") + " timeout -s KILL 20 " + SIPMSS_CLI + " simplify " + P("in.ply") +
      " " + P("out.ply") + options + "; echo status=$?");
    EXPECT_NE(out.find("status=0"), std::string::npos) << algorithm << "\n" << out;
    EXPECT_EQ(ReadAll(this->dir / "out.ply"), ReadAll(this->dir / "ref.ply")) << algorithm;
    EXPECT_TRUE(fs::is_empty(this->dir / "tmp")) << algorithm; // the copy was never visible
    fs::remove(this->dir / "out.ply");
  }
  // gzip through a pipe (/dev/stdin) works too.
  {
    const std::string out = RunShell("gzip -c " + P("grid.ply") + " | " + SIPMSS_CLI +
      " simplify /dev/stdin " + P("out.ply") + " --grid 20 --quiet; echo status=$?");
    EXPECT_NE(out.find("status=0"), std::string::npos) << out;
    Result ref = RunCli("simplify " + P("grid.ply") + " " + P("ref.ply") + " --grid 20 --quiet");
    EXPECT_EQ(ReadAll(this->dir / "out.ply"), ReadAll(this->dir / "ref.ply"));
  }
  // Nobody writes: the first Ctrl-C stops the run (it blocked in open(2), deaf to SIGINT).
  for (const std::string options : { "", "--threads 1", "--algorithm decimate" })
  {
    const std::string out = InterruptAfter(
      "simplify " + P("in.ply") + " " + P("never.ply") + " --quiet " + options, 0.5);
    EXPECT_NE(out.find("status=130"), std::string::npos) << options << "\n" << out;
    EXPECT_NE(out.find("sipmss: interrupted; nothing was written"), std::string::npos) << out;
    EXPECT_LT(SecondsOf(out), 1.0) << options << "\n" << out;
    EXPECT_FALSE(fs::exists(this->dir / "never.ply"));
  }
}

TEST_F(CLI, CtrlCStopsTheReaderInsideAHugeCommentLine)
{
  // A .gz holding a comment line of 8 GiB (8 MB compressed): the readers asked for an abort
  // only between chunks, so a run went on reading for many seconds after Ctrl-C.
  {
    const std::string chunk = std::string(64u << 20, 'x');
    std::vector<unsigned char> member(compressBound(uLong(chunk.size())) + 64);
    z_stream z{};
    ASSERT_EQ(deflateInit2(&z, 9, Z_DEFLATED, 15 + 16, 9, Z_DEFAULT_STRATEGY), Z_OK);
    z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(chunk.data()));
    z.avail_in = uInt(chunk.size());
    z.next_out = member.data();
    z.avail_out = uInt(member.size());
    ASSERT_EQ(deflate(&z, Z_FINISH), Z_STREAM_END);
    member.resize(z.total_out);
    deflateEnd(&z);
    std::ofstream f(this->dir / "huge.obj.gz", std::ios::binary);
    const std::string head = "# ";
    gzFile g = gzopen(P("head.gz").c_str(), "wb");
    gzwrite(g, head.data(), unsigned(head.size()));
    gzclose(g);
    f << ReadAll(this->dir / "head.gz");
    fs::remove(this->dir / "head.gz");
    for (int i = 0; i < 128; ++i) // gzip members concatenate: 128 x 64 MiB of 'x'
    {
      f.write(reinterpret_cast<const char*>(member.data()), std::streamsize(member.size()));
    }
  }
  for (const std::string options : { "", "--threads 1", "--algorithm decimate" })
  {
    const std::string out = InterruptAfter(
      "simplify " + P("huge.obj.gz") + " " + P("out.ply") + " --quiet " + options, 0.5);
    EXPECT_NE(out.find("status=130"), std::string::npos) << options << "\n" << out;
    EXPECT_LT(SecondsOf(out), 1.0) << options << "\n" << out;
  }
}

TEST_F(CLI, EmptyAndDegenerateInputsGiveOneNamedMessage)
{
  std::ofstream(this->dir / "comments.obj") << "# nothing here\n";
  std::ofstream(this->dir / "points.obj") << "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
  std::ofstream(this->dir / "degenerate.obj") << "v 0 0 0\nv 1 0 0\nf 1 1 2\nf 1 2\n";
  std::ofstream(this->dir / "zeros.ply", std::ios::binary) << std::string(84, '\0');
  const struct
  {
    std::string file, message;
  } cases[] = {
    { "comments.obj", ": nothing to simplify: the input has no valid triangle\n" },
    { "points.obj", ": nothing to simplify: the input has no valid triangle\n" },
    { "degenerate.obj",
      ": nothing to simplify: the input has no valid triangle (2 degenerate faces were dropped)\n" },
    { "zeros.ply", ": file is not a mesh file (unknown format: its first 84 bytes are all zero; "
                   "expected PLY, STL or OBJ), at byte 0\n" },
  };
  for (const auto& c : cases)
  {
    for (const std::string algorithm : { "cluster", "decimate", "two-stage" })
    {
      Result r = RunCli("simplify " + P(c.file) + " " + P("out.ply") + " --quiet --algorithm " + algorithm);
      EXPECT_EQ(r.status, 1) << c.file << " " << algorithm << "\n" << r.out;
      EXPECT_EQ(r.out, "sipmss: error: " + P(c.file) + c.message) << c.file << " " << algorithm;
      EXPECT_FALSE(fs::exists(this->dir / "out.ply"));
    }
    // info describes a valid file and warns in the same words; an unreadable one is the same error.
    Result i = RunCli("info " + P(c.file));
    if (c.file == "zeros.ply")
    {
      EXPECT_EQ(i.status, 1) << i.out;
      EXPECT_EQ(i.out, "sipmss: error: " + P(c.file) + c.message);
    }
    else
    {
      EXPECT_EQ(i.status, 0) << i.out;
      EXPECT_NE(i.out.find("sipmss: warning: " + P(c.file) + c.message), std::string::npos) << i.out;
    }
  }
}

TEST_F(CLI, AFifoInputOnAFullTemporaryDiskIsANamedError)
{
  // The copy of a FIFO input goes to $TMPDIR: a full one is an error naming the input and the
  // directory, and leaves nothing there.
  const fs::path mnt = this->dir / "full";
  fs::create_directory(mnt);
  if (std::system(("mount -t tmpfs -o size=64k tmpfs " + mnt.string() + " 2>/dev/null").c_str()) != 0)
  {
    GTEST_SKIP() << "cannot mount a tmpfs here (needs root): skipping the full-disk test";
  }
  WriteGrid(P("grid.ply"), 100); // 120 KiB
  ASSERT_EQ(::mkfifo(P("in.ply").c_str(), 0600), 0);
  const std::string out = RunShell("cat " + P("grid.ply") + " > " + P("in.ply") + " 2>/dev/null & TMPDIR=" +
    mnt.string() + " timeout -s KILL 20 " + SIPMSS_CLI + " simplify " + P("in.ply") + " " +
    P("out.ply") + " --quiet; echo status=$?; wait");
  const bool empty = fs::is_empty(mnt);
  EXPECT_EQ(std::system(("umount " + mnt.string()).c_str()), 0);
  EXPECT_NE(out.find("status=1\n"), std::string::npos) << out;
  EXPECT_NE(out.find("sipmss: error: " + P("in.ply") +
              ": file cannot be copied (a pipe or device can be read only once) to a temporary file in " +
              mnt.string() + ": No space left on device"),
    std::string::npos)
    << out;
  EXPECT_TRUE(empty);
  EXPECT_FALSE(fs::exists(this->dir / "out.ply"));
}

TEST_F(CLI, ManyVertexPropertiesStayWithinTheBudget)
{
  // 9 vertices with 40,000 float properties each (1.4 MB of vertex data): every algorithm at an
  // 8 MB budget peaks within the budget plus a small constant (its buffers are sized by bytes,
  // not by 16K vertices times every property: 2.6 GB).
  SKIP_UNDER_ADDRESS_SANITIZER();
  const int props = 40000;
  {
    std::ofstream f(P("props.ply"), std::ios::binary);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex 9\n"
         "property float x\nproperty float y\nproperty float z\n";
    for (int i = 0; i < props; ++i)
    {
      f << "property float s" << i << "\n";
    }
    f << "element face 8\nproperty list uchar int vertex_indices\nend_header\n";
    std::vector<float> record(3 + std::size_t(props));
    for (int j = 0; j < 3; ++j)
    {
      for (int i = 0; i < 3; ++i)
      {
        std::fill(record.begin(), record.end(), float(i + j));
        record[0] = float(i), record[1] = float(j), record[2] = 0;
        f.write(reinterpret_cast<const char*>(record.data()), std::streamsize(4 * record.size()));
      }
    }
    for (int j = 0; j < 2; ++j)
    {
      for (int i = 0; i < 2; ++i)
      {
        const int a = j * 3 + i, b = a + 1, c = a + 4, d = a + 3;
        const int t[2][3] = { { a, b, c }, { a, c, d } };
        for (const auto& tri : t)
        {
          const char three = 3;
          f.write(&three, 1);
          f.write(reinterpret_cast<const char*>(tri), 12);
        }
      }
    }
  }
  if (RunCommand("/usr/bin/time -f %M true").status != 0)
  {
    GTEST_SKIP() << "/usr/bin/time is missing (Debian package time, installed by scripts/setup)";
  }
  for (const char* run : { "--algorithm cluster --grid 2", "--algorithm decimate --target 4",
         "--algorithm two-stage --grid 2 --target 4" })
  {
    const Result r = RunCommand("/usr/bin/time -f 'peak=%M' " + std::string(SIPMSS_CLI) + " simplify " +
      P("props.ply") + " " + P("out.ply") + " --memory-mb 8 --quiet --tmpdir " + this->dir.string() +
      " " + run);
    ASSERT_EQ(r.status, 0) << run << "\n" << r.out;
    const std::size_t at = r.out.rfind("peak=");
    ASSERT_NE(at, std::string::npos) << r.out;
    const double peakMB = std::atof(r.out.c_str() + at + 5) / 1024.0;
    EXPECT_LT(peakMB, 8 + 32) << run << ": peak RSS " << peakMB << " MB at an 8 MB budget";
    Result info = RunCli("info " + P("out.ply"));
    EXPECT_NE(info.out.find("\"s39999\""), std::string::npos) << run; // the properties are kept
  }
}

namespace
{
// A fan of n triangles around vertex 0 (a disk with its center raised), binary PLY.
void WriteFan(const std::string& path, int n)
{
  std::ofstream f(path, std::ios::binary);
  f << "ply\nformat binary_little_endian 1.0\nelement vertex " << n + 1
    << "\nproperty float x\nproperty float y\nproperty float z\nelement face " << n - 1
    << "\nproperty list uchar int vertex_indices\nend_header\n";
  std::vector<float> xyz(3 * std::size_t(n + 1), 0.0f);
  xyz[2] = 0.1f;
  for (int i = 0; i < n; ++i)
  {
    const double a = 6.283185307179586 * i / n;
    xyz[3 * std::size_t(i + 1)] = float(std::cos(a));
    xyz[3 * std::size_t(i + 1) + 1] = float(std::sin(a));
  }
  f.write(reinterpret_cast<const char*>(xyz.data()), std::streamsize(xyz.size() * 4));
  std::vector<char> faces(13 * std::size_t(n - 1));
  char* p = faces.data();
  for (int i = 1; i < n; ++i)
  {
    const int t[3] = { 0, i, i + 1 };
    *p++ = 3;
    std::memcpy(p, t, 12);
    p += 12;
  }
  f.write(faces.data(), std::streamsize(faces.size()));
}
} // namespace

TEST_F(CLI, AVertexOfHighValenceDecimatesAndStopsOnCtrlC)
{
  // One vertex in 200,000 triangles (a fan, or an OBJ polygon with 200,000 corners): the
  // duplicate search, the quadrics and the sweep took time quadratic in its valence (more than
  // 7 minutes, deaf to Ctrl-C), and out of core the duplicate search crashed. A hang guard of
  // 60 s; the run takes about a second.
  WriteFan(P("fan.ply"), 200000);
  {
    std::ofstream f(P("polygon.obj"));
    for (int i = 0; i < 200000; ++i)
    {
      const double a = 6.283185307179586 * i / 200000;
      f << "v " << std::cos(a) << " " << std::sin(a) << " " << 0.01 * std::sin(7 * a) << "\n";
    }
    f << "f";
    for (int i = 1; i <= 200000; ++i)
    {
      f << " " << i;
    }
    f << "\n";
  }
  for (const std::string input : { "fan.ply", "polygon.obj" })
  {
    std::string reference;
    for (const std::string options : { "--algorithm decimate --memory-mb 8 --threads 1",
           "--algorithm decimate --memory-mb 8 --threads 2", "--algorithm decimate --threads 2",
           "--algorithm two-stage --memory-mb 8" })
    {
      const Result r = RunCommand("timeout -s KILL 60 " + std::string(SIPMSS_CLI) + " simplify " +
        P(input) + " " + P("out.ply") + " --quiet --target 100 --tmpdir " + this->dir.string() +
        " " + options);
      ASSERT_EQ(r.status, 0) << input << " " << options << "\n" << r.out;
      const Result info = RunCli("info " + P("out.ply"));
      const auto at = info.out.find("\"triangles\": ");
      ASSERT_NE(at, std::string::npos) << info.out;
      const long triangles = std::atol(info.out.c_str() + at + 13);
      EXPECT_GT(triangles, 0) << input << " " << options;
      EXPECT_LE(triangles, 100) << input << " " << options;
      if (options.find("two-stage") == std::string::npos)
      {
        // The same result on one thread or two, in core or out of core.
        const std::string out = ReadAll(this->dir / "out.ply");
        if (reference.empty())
        {
          reference = out;
        }
        EXPECT_EQ(out, reference) << input << " " << options;
      }
    }
  }
  // Ctrl-C: a fan of 1,000,000 triangles runs for seconds; the first Ctrl-C ends it at once.
  WriteFan(P("big.ply"), 1000000);
  for (const std::string options : { "--memory-mb 8", "--memory-mb 8 --threads 1", "" })
  {
    for (const double delay : { 0.4, 1.2 })
    {
      const std::string out = InterruptAfter("simplify " + P("big.ply") + " " + P("never.ply") +
          " --quiet --algorithm decimate --target 100 --tmpdir " + this->dir.string() + " " + options,
        delay);
      EXPECT_NE(out.find("status=130"), std::string::npos) << options << "\n" << out;
      EXPECT_LT(SecondsOf(out), 0.5) << options << " after " << delay << " s\n" << out;
      EXPECT_FALSE(fs::exists(this->dir / "never.ply"));
    }
  }
}

TEST_F(CLI, SeveralTemporaryDirectoriesFallBackWhenOneIsFull)
{
  // Two --tmpdir, the first a full 1 MiB tmpfs: the run goes on in the second, says so, and
  // writes the same mesh; with the full one alone it fails at once, naming it and its room.
  WriteGrid(P("grid.ply"), 200); // 80,000 triangles: about 4 MB of block files at 64 KiB
  const fs::path mnt = this->dir / "small", other = this->dir / "other";
  fs::create_directory(mnt);
  fs::create_directory(other);
  if (std::system(("mount -t tmpfs -o size=1m tmpfs " + mnt.string() + " 2>/dev/null").c_str()) != 0)
  {
    GTEST_SKIP() << "cannot mount a tmpfs here (needs root): skipping the full-directory test";
  }
  const std::string run = "simplify " + P("grid.ply") + " " + P("out.ply") +
    " --algorithm decimate --target 1000 --memory-mb 0.0625 --quiet";
  Result ref = RunCli(run + " --tmpdir " + other.string());
  ASSERT_EQ(ref.status, 0) << ref.out;
  const std::string reference = ReadAll(this->dir / "out.ply");
  fs::remove(this->dir / "out.ply");
  Result r = RunCli(run + " --tmpdir " + mnt.string() + " --tmpdir " + other.string() +
    " --stats-json " + P("s.json"));
  Result alone = RunCli(run + " --tmpdir " + mnt.string());
  const bool mntEmpty = fs::is_empty(mnt);
  EXPECT_EQ(std::system(("umount " + mnt.string()).c_str()), 0);
  EXPECT_EQ(r.status, 0) << r.out;
  EXPECT_NE(r.out.find("sipmss: warning: temporary directory " + mnt.string() + ": "),
    std::string::npos) << r.out;
  EXPECT_NE(r.out.find("block files go to " + other.string()), std::string::npos) << r.out;
  EXPECT_EQ(ReadAll(this->dir / "out.ply"), reference);
  EXPECT_NE(ReadAll(this->dir / "s.json").find("\"notes\": ["), std::string::npos);
  EXPECT_EQ(alone.status, 1) << alone.out;
  EXPECT_NE(alone.out.find(mnt.string() + ": 1.0 MiB free"), std::string::npos) << alone.out;
  EXPECT_NE(alone.out.find("--tmpdir"), std::string::npos) << alone.out;
  EXPECT_TRUE(mntEmpty);
  EXPECT_TRUE(fs::is_empty(other));
}

TEST_F(CLI, TemporaryDiskStaysWithinTheDeclaredStructures)
{
  // The block files' peak (storage.peak_file_bytes) stays within the structures the run
  // declares from the header's counts (storage.declared_bytes, the paper's C), out of core.
  WriteGrid(P("grid.ply"), 150);
  for (const std::string run : { "--algorithm decimate --target 1000", "--algorithm cluster --grid 40" })
  {
    Result r = RunCli("simplify " + P("grid.ply") + " " + P("out.ply") + " --quiet --memory-mb 0.0625 " +
      run + " --tmpdir " + this->dir.string() + " --stats-json " + P("s.json"));
    ASSERT_EQ(r.status, 0) << run << "\n" << r.out;
    const std::string json = ReadAll(this->dir / "s.json");
    auto number = [&](const std::string& key) {
      const auto at = json.find("\"" + key + "\": ");
      return at == std::string::npos ? 0.0 : std::atof(json.c_str() + at + key.size() + 4);
    };
    const double peak = number("peak_file_bytes"), declared = number("declared_bytes");
    EXPECT_GT(peak, 0) << run << "\n" << json;
    EXPECT_GT(declared, 0) << run << "\n" << json;
    EXPECT_LE(peak, declared) << run;
  }
}

// The default budget is automatic: under a `ulimit -v` smaller than the run's in-core need
// (about 100 MB for a million triangles) the default run goes out of core and succeeds, and
// says why; an explicitly unbounded run fails with an error that names the phase and the
// option, never a bare std::bad_alloc, and writes nothing.
TEST_F(CLI, DefaultBudgetFollowsTheAddressSpaceLimit)
{
  SKIP_UNDER_ADDRESS_SANITIZER();
  WriteGrid(P("grid.ply"), 700); // 980,000 triangles
  const std::string limit = "ulimit -v 100000; ";
  for (const char* algorithm : { "decimate", "two-stage", "cluster" })
  {
    const std::string target = std::string(algorithm) == "cluster" ? "" : " --target 1000";
    Result r = RunCommand(limit + SIPMSS_CLI + " simplify " + P("grid.ply") + " " + P("out.ply") +
      " --algorithm " + algorithm + target + " --quiet --stats-json " + P("s.json") +
      " --tmpdir " + this->dir.string());
    ASSERT_EQ(r.status, 0) << algorithm << "\n" << r.out;
    std::ifstream js(P("s.json"));
    const std::string json((std::istreambuf_iterator<char>(js)), std::istreambuf_iterator<char>());
    EXPECT_NE(json.find("RLIMIT_AS"), std::string::npos) << json;
    if (std::string(algorithm) == "decimate")
    {
      EXPECT_NE(json.find("\"used_out_of_core\": true"), std::string::npos) << json;
    }
    fs::remove(P("out.ply"));
  }
  Result u = RunCommand(limit + SIPMSS_CLI + " simplify " + P("grid.ply") + " " + P("out.ply") +
    " --algorithm decimate --target 1000 --quiet --memory-mb unbounded");
  EXPECT_EQ(u.status, 1) << u.out;
  EXPECT_NE(u.out.find("out of memory in the "), std::string::npos) << u.out;
  EXPECT_NE(u.out.find("--memory-mb"), std::string::npos) << u.out;
  EXPECT_EQ(u.out.find("bad_alloc"), std::string::npos) << u.out;
  EXPECT_FALSE(fs::exists(P("out.ply")));
  for (const auto& e : fs::directory_iterator(this->dir))
  {
    EXPECT_EQ(e.path().filename().string().rfind(".sipmss-", 0), std::string::npos)
      << "left behind: " << e.path();
  }
}
