// sipmss: simplify huge triangle meshes under a fixed memory budget, compare and inspect meshes.
//
//   sipmss simplify INPUT OUTPUT [--algorithm cluster|decimate|two-stage] [options by topic:
//                  target, clustering, boundaries and welding, memory and storage, output;
//                  `sipmss simplify --help`]
//   sipmss compare REFERENCE CANDIDATE [--samples N]
//   sipmss info FILE
//   sipmss --version
//
// Exit status: 0 success, 1 input or I/O error, 2 usage error.
#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Simplify.h"
#include "sipmss/io/MeshIO.h"
#include "sipmss/io/VectorSink.h"

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <malloc.h>
#include <sys/resource.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <optional>
#include <random>

namespace fs = std::filesystem;
using namespace sipmss;

namespace
{

// SIGINT/SIGTERM: the first one asks the run to stop (the cores poll Progress::Aborted at least
// every 0.1 s), so the normal unwinding removes the temporary output and the DML's block files;
// a second one terminates at once.
volatile std::sig_atomic_t g_interrupted = 0;

extern "C" void OnInterrupt(int sig)
{
  g_interrupted = sig;
  std::signal(sig, SIG_DFL);
}

// info and compare write nothing and hold nothing to clean up (their inputs are read in place):
// the first SIGINT/SIGTERM ends them at once, wherever they are (a read blocked on a FIFO, a
// long sampling loop), with simplify's message and status. Only async-signal-safe calls.
extern "C" void OnInterruptReadOnly(int sig)
{
  static const char message[] = "sipmss: interrupted; nothing was written\n";
  const ssize_t ignored = ::write(STDERR_FILENO, message, sizeof(message) - 1);
  (void)ignored;
  ::_exit(128 + sig);
}

// A progress bar on a terminal: the phase, percent, elapsed time and an estimate of the time left
// (from the run's progress so far); silent otherwise. Aborted() on SIGINT/SIGTERM.
class TerminalProgress final : public algorithms::Progress
{
public:
  explicit TerminalProgress(bool enabled)
    : enabled_(enabled)
    , start_(std::chrono::steady_clock::now())
  {
    this->SetInterval(0.1);
  }
  ~TerminalProgress() override { this->Clear(); }
  void Report(double fraction, const char* phase) override
  {
    if (!this->enabled_)
    {
      return;
    }
    const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - this->start_).count();
    const int width = 30;
    const int filled = static_cast<int>(fraction * width + 0.5);
    std::string left = "";
    if (fraction >= 0.02 && fraction < 1 && elapsed >= 1)
    {
      left = ", ~" + Clock(elapsed * (1 - fraction) / fraction) + " left";
    }
    std::fprintf(stderr, "\r[%.*s%*s] %3d%% %-12s %s elapsed%s   ", filled,
      "##############################", width - filled, "", static_cast<int>(fraction * 100),
      phase, Clock(elapsed).c_str(), left.c_str());
    std::fflush(stderr);
    this->drawn_ = true;
  }
  bool Aborted() override { return g_interrupted != 0; }
  void Clear()
  {
    if (this->drawn_)
    {
      std::fprintf(stderr, "\r%*s\r", 90, "");
      this->drawn_ = false;
    }
  }

private:
  static std::string Clock(double seconds)
  {
    const long s = std::lround(seconds);
    char buf[32];
    if (s >= 3600)
    {
      std::snprintf(buf, sizeof(buf), "%ld:%02ld:%02ld", s / 3600, s / 60 % 60, s % 60);
    }
    else
    {
      std::snprintf(buf, sizeof(buf), "%ld:%02ld", s / 60, s % 60);
    }
    return buf;
  }

  bool enabled_;
  bool drawn_ = false;
  std::chrono::steady_clock::time_point start_;
};

// A hidden temporary name beside `target` (same directory, so the rename is atomic; the
// extension stays last so a writer picks the format from it): .sipmss-<pid>-<target's name>.
// Commit() renames it onto target; otherwise the temporary is removed. A run killed outright
// (SIGKILL, power loss) cannot remove its temporary: the next run to the same target removes those
// of processes that no longer exist (like the DML's stale block directories; same caveat: pids
// mean something on this host only).
class TemporaryBeside
{
public:
  explicit TemporaryBeside(fs::path target)
    : target_(std::move(target))
  {
    this->temp_ = this->target_.parent_path() /
      (".sipmss-" + std::to_string(::getpid()) + "-" + this->target_.filename().string());
    this->RemoveStaleTemporaries();
  }
  TemporaryBeside(const TemporaryBeside&) = delete;
  TemporaryBeside& operator=(const TemporaryBeside&) = delete;
  ~TemporaryBeside()
  {
    if (!this->committed_)
    {
      std::error_code ec;
      fs::remove(this->temp_, ec);
    }
  }
  const fs::path& Temp() const { return this->temp_; }
  void Commit()
  {
    std::error_code ec;
    fs::rename(this->temp_, this->target_, ec);
    if (ec)
    {
      throw io::MeshIOError(this->target_.string() + ": cannot write: " + ec.message());
    }
    this->committed_ = true;
  }

private:
  // Regular files .sipmss-<pid>-<target's name> beside target whose pid has no process.
  void RemoveStaleTemporaries() const
  {
    const std::string suffix = "-" + this->target_.filename().string();
    const fs::path dir = this->target_.parent_path().empty() ? fs::path(".") : this->target_.parent_path();
    std::error_code ec;
    for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec))
    {
      const std::string name = it->path().filename().string();
      if (name.size() <= 8 + suffix.size() || name.compare(0, 8, ".sipmss-") != 0 ||
        name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0)
      {
        continue;
      }
      const std::string digits = name.substr(8, name.size() - 8 - suffix.size());
      if (digits.find_first_not_of("0123456789") != std::string::npos || digits.size() > 9)
      {
        continue;
      }
      const long pid = std::stol(digits);
      struct stat st{};
      if (pid > 0 && pid != ::getpid() && ::kill(static_cast<pid_t>(pid), 0) != 0 &&
        errno == ESRCH && ::lstat(it->path().c_str(), &st) == 0 && S_ISREG(st.st_mode))
      {
        std::error_code rm;
        fs::remove(it->path(), rm);
      }
    }
  }

  fs::path target_, temp_;
  bool committed_ = false;
};

// Writes a streamed mesh to a temporary name beside OUTPUT; Commit() renames it into place. If
// the run fails or is abandoned, the temporary file is removed and OUTPUT is untouched.
class FileSink final : public io::MeshSink
{
public:
  explicit FileSink(fs::path output)
    : file_(std::move(output))
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->writer_ = io::MeshWriter::Create(this->file_.Temp().string(), false);
    this->writer_->Begin(h.vertexCount, h.faceCount, h.layout);
  }
  void Vertices(const io::VertexChunk& c) override { this->writer_->Vertices(c); }
  void Triangles(const std::uint32_t* i, std::size_t n) override { this->writer_->Triangles(i, n); }
  void End(const io::ReadStats&) override { this->writer_->End(); }
  void Commit()
  {
    this->writer_.reset();
    this->file_.Commit();
  }

private:
  TemporaryBeside file_; // declared first: the writer closes before the temporary is removed
  std::unique_ptr<io::MeshWriter> writer_;
};

// Where writing `path` lands: the file a symlink points to (the link stays a link, its target
// gets the new content), else path itself.
fs::path WriteTarget(const fs::path& path)
{
  std::error_code ec;
  if (fs::is_symlink(path, ec))
  {
    const fs::path target = fs::weakly_canonical(path, ec);
    if (!ec)
    {
      return target;
    }
  }
  return path;
}

// A small file written whole to a temporary name beside its target (through a symlink, the
// link's target): any write failure is an error naming the user's path, and the temporary is
// removed. Commit() renames it into place.
class PendingFile
{
public:
  PendingFile(const std::string& path, const std::string& content)
    : path_(path)
    , file_(WriteTarget(path))
  {
    const int fd = ::open(this->file_.Temp().c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0666);
    if (fd < 0)
    {
      this->Fail(errno);
    }
    std::size_t done = 0;
    while (done < content.size())
    {
      const ssize_t n = ::write(fd, content.data() + done, content.size() - done);
      if (n < 0 && errno == EINTR)
      {
        continue;
      }
      if (n <= 0)
      {
        const int err = n < 0 ? errno : EIO;
        ::close(fd);
        this->Fail(err);
      }
      done += std::size_t(n);
    }
    if (::close(fd) != 0)
    {
      this->Fail(errno);
    }
  }
  void Commit() { this->file_.Commit(); }

private:
  [[noreturn]] void Fail(int err) const
  {
    throw io::MeshIOError(this->path_ + ": cannot write the statistics: " + std::strerror(err));
  }
  std::string path_;
  TemporaryBeside file_;
};

// Gathers the header, counts and bounds (for info).
class InfoSink final : public io::MeshSink
{
public:
  void Begin(const io::MeshHeader& h) override { this->header = h; }
  void Vertices(const io::VertexChunk& c) override
  {
    float lo[3] = { HUGE_VALF, HUGE_VALF, HUGE_VALF }, hi[3] = { -HUGE_VALF, -HUGE_VALF, -HUGE_VALF };
    for (std::size_t i = 0; i < c.count; ++i)
    {
      for (int k = 0; k < 3; ++k)
      {
        lo[k] = std::min(lo[k], c.xyz[3 * i + k]);
        hi[k] = std::max(hi[k], c.xyz[3 * i + k]);
      }
    }
    for (int k = 0; k < 3; ++k)
    {
      this->bounds[2 * k] = std::min<double>(this->bounds[2 * k], lo[k]);
      this->bounds[2 * k + 1] = std::max<double>(this->bounds[2 * k + 1], hi[k]);
    }
  }
  void Triangles(const std::uint32_t*, std::size_t) override {}
  void End(const io::ReadStats& s) override { this->stats = s; }
  io::MeshHeader header;
  io::ReadStats stats;
  std::array<double, 6> bounds{ HUGE_VAL, -HUGE_VAL, HUGE_VAL, -HUGE_VAL, HUGE_VAL, -HUGE_VAL };
};

double PeakRssMB()
{
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return double(ru.ru_maxrss) / 1024.0; // ru_maxrss is in KiB on Linux
}

fs::path LodPath(const fs::path& output, int level)
{
  std::string stem = output.stem().string();
  std::string ext = output.extension().string();
  return output.parent_path() / (stem + "_lod" + std::to_string(level) + ext);
}

// Refuses any path this run would write (OUTPUT, its levels of detail, the statistics) that is
// the input file itself: the same device and inode, so `./in.ply`, a symlink or a hard link to
// the input are caught too. The input is the user's data; a run never replaces it.
void RefuseToOverwriteInput(const std::string& input, const std::vector<fs::path>& writes)
{
  struct stat in{};
  if (::stat(input.c_str(), &in) != 0)
  {
    return; // the reader reports a missing or unreadable input with its own message
  }
  for (const auto& w : writes)
  {
    struct stat out{};
    if (::stat(w.c_str(), &out) == 0 && out.st_dev == in.st_dev && out.st_ino == in.st_ino)
    {
      throw CLI::ValidationError(w.string() + ": is the input file " + input +
        " (the same file); refusing to overwrite the input, choose another output path");
    }
  }
}

// The command line of `simplify`: the request (the one every front end fills) and the CLI's own
// paths and switches.
struct SimplifyArgs
{
  std::string input, output, statsJson;
  std::string algorithm = "cluster";
  std::string memory = "auto";
  std::string mode = "auto";
  std::vector<double> bounds;
  bool quiet = false;
  algorithms::SimplifyRequest request;
};

// A path this run will write must be a writable place: its directory exists and is writable, and
// what is there now, if anything, is a regular file (never a directory, FIFO, device or socket).
// Checked before any work, naming the user's path.
void CheckWritablePath(const fs::path& path, const char* what)
{
  const fs::path target = WriteTarget(path);
  const std::string named =
    path.string() + (target != path ? " (a symlink to " + target.string() + ")" : std::string());
  const fs::path dir = target.parent_path().empty() ? fs::path(".") : target.parent_path();
  std::error_code ec;
  if (!fs::is_directory(dir, ec))
  {
    throw io::MeshIOError(named + ": cannot write the " + what + ": the directory " +
      dir.string() + (fs::exists(dir, ec) ? " is not a directory" : " does not exist"));
  }
  if (::access(dir.c_str(), W_OK | X_OK) != 0)
  {
    throw io::MeshIOError(named + ": cannot write the " + what + ": the directory " +
      dir.string() + " is not writable (" + std::strerror(errno) + ")");
  }
  const fs::file_status st = fs::symlink_status(target, ec);
  if (fs::exists(st) && !fs::is_regular_file(st))
  {
    throw io::MeshIOError(named + ": cannot write the " + what + ": " +
      (fs::is_directory(st) ? "it is a directory" : "it exists and is not a regular file") +
      " (it is never replaced)");
  }
}

// Everything about OUTPUT, the levels of detail and the statistics file that can be known before
// the run: the input is not among them, the mesh formats are known, the places writable.
void CheckOutputs(const SimplifyArgs& a)
{
  std::vector<fs::path> writes{ fs::path(a.output) };
  const int lods = a.request.levelsOfDetail;
  for (int level = 0; level < lods && lods > 1; ++level)
  {
    writes.push_back(LodPath(a.output, level));
  }
  if (!a.statsJson.empty())
  {
    writes.emplace_back(a.statsJson);
  }
  RefuseToOverwriteInput(a.input, writes);
  io::MeshWriter::CheckExtension(a.output);
  io::MeshWriter::CheckExtension(WriteTarget(a.output), a.output + " (through its symlink)");
  for (std::size_t i = 0; i < writes.size(); ++i)
  {
    const bool stats = !a.statsJson.empty() && i + 1 == writes.size();
    CheckWritablePath(writes[i], stats ? "statistics" : i == 0 ? "output" : "level of detail");
  }
}

int RunSimplify(const SimplifyArgs& a)
{
  CheckOutputs(a);
  const algorithms::SimplifyRequest& request = a.request;
  const bool tty = !a.quiet && ::isatty(STDERR_FILENO);
  TerminalProgress progress(tty);
  const std::vector<std::string>& tmpdirs = request.temporaryDirectories;
  const algorithms::MeshSource source =
    algorithms::FileSource(a.input, tmpdirs.empty() ? std::string() : tmpdirs.front());
  // Block directories left by runs that were killed (kill -9) are removed first.
  {
    std::vector<std::string> dirs = tmpdirs;
    if (dirs.empty())
    {
      const char* t = std::getenv("TMPDIR");
      dirs.emplace_back(t && *t ? t : "/tmp");
    }
    for (const auto& d : dirs)
    {
      std::error_code ec;
      if (fs::is_directory(d, ec))
      {
        storage::DML::CleanStaleDirectories(d);
      }
    }
  }

  std::vector<std::unique_ptr<FileSink>> lodSinks;
  FileSink sink(WriteTarget(a.output));
  algorithms::LevelCallback onLevel;
  if (request.levelsOfDetail > 1)
  {
    onLevel = [&](int level, const std::function<void(io::MeshSink&)>& emit) {
      auto s = std::make_unique<FileSink>(WriteTarget(LodPath(a.output, level)));
      emit(*s);
      lodSinks.push_back(std::move(s));
    };
  }
  const auto start = std::chrono::steady_clock::now();
  const algorithms::RunStats stats = [&] {
    try
    {
      return algorithms::Simplify(request, source, sink, progress, onLevel);
    }
    catch (const algorithms::MissingArrayError& e)
    {
      // (the core does not know the file's name)
      throw io::MeshIOError(a.input + ": " + e.what());
    }
  }();
  progress.Clear();
  const double seconds =
    std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  // The statistics are written to a temporary file first: a failure (a full disk) is an error
  // before anything is renamed into place.
  std::optional<PendingFile> statsFile;
  if (!a.statsJson.empty())
  {
    nlohmann::json j;
    j["algorithm"] = a.algorithm;
    // The grid cluster and two-stage ran on (two-stage's default follows a large target).
    if (stats.gridDimension > 0)
    {
      j["grid"] = stats.gridDimension;
    }
    else
    {
      j["grid"] = nullptr;
    }
    j["input"] = a.input;
    j["output"] = a.output;
    j["input_vertices"] = stats.inputVertices;
    j["input_triangles"] = stats.inputTriangles;
    j["dropped_input_faces"] = stats.droppedInputFaces;
    j["pruned_components"] = stats.prunedComponents;
    j["pruned_triangles"] = stats.prunedTriangles;
    j["output_vertices"] = stats.outputVertices;
    j["output_triangles"] = stats.outputTriangles;
    j["seconds"] = seconds;
    j["peak_rss_mb"] = PeakRssMB();
    j["memory_budget_bytes"] = stats.memoryBudgetBytes;
    j["memory_budget"] = stats.memoryBudgetOrigin.empty() ? std::string("given") : stats.memoryBudgetOrigin;
    // The input's layout: the share of faces far from their neighbours in index order (null: not
    // measured, the run fit in memory) and whether it was reordered first.
    if (stats.layoutFarFraction >= 0)
    {
      j["layout_far_fraction"] = stats.layoutFarFraction;
    }
    else
    {
      j["layout_far_fraction"] = nullptr;
    }
    j["reordered"] = stats.reordered;
    // The layout step's parts, when it ran: seconds, the DML's I/O, block files at the end.
    nlohmann::json layoutSteps = nlohmann::json::array();
    for (const auto& p : stats.layoutSteps)
    {
      layoutSteps.push_back({ { "name", p.name }, { "seconds", p.seconds },
        { "bytes_read", p.bytesRead }, { "bytes_written", p.bytesWritten },
        { "file_bytes", p.fileBytes } });
    }
    j["layout_steps"] = layoutSteps;
    // The error of the run's merges relative to the input's bounding-box diagonal, and that
    // diagonal (docs/architecture.md, "Error bound").
    if (stats.achievedError >= 0)
    {
      j["achieved_error"] = stats.achievedError;
    }
    else
    {
      j["achieved_error"] = nullptr;
    }
    j["diagonal"] = stats.errorDiagonal;
    j["warnings"] = stats.warnings;
    nlohmann::json phases = nlohmann::json::array();
    for (const auto& p : stats.phases)
    {
      phases.push_back({ { "name", p.name }, { "seconds", p.seconds },
        { "mode", storage::ToString(p.mode) } });
    }
    j["phases"] = phases;
    // The decimation's passes (docs/architecture.md "Algorithm I and the two-stage method in
    // brief"): sizes, work, and the seconds and the DML's I/O of their four steps, the I/O also
    // by array (out of core; empty in core).
    nlohmann::json passes = nlohmann::json::array();
    for (const auto& p : stats.passes)
    {
      nlohmann::json steps;
      for (const auto& [name, st] : { std::pair{ "sweep", &p.sweep }, std::pair{ "order", &p.order },
             std::pair{ "step", &p.step }, std::pair{ "compact", &p.compact } })
      {
        nlohmann::json arrays = nlohmann::json::array();
        for (const auto& a : st->arrays)
        {
          arrays.push_back({ { "name", a.name }, { "misses", a.misses },
            { "bytes_read", a.bytesRead }, { "bytes_written", a.bytesWritten } });
        }
        steps[name] = { { "seconds", st->seconds }, { "bytes_read", st->bytesRead },
          { "bytes_written", st->bytesWritten }, { "misses", st->misses }, { "arrays", arrays } };
      }
      passes.push_back({ { "run", p.run }, { "vertices", p.vertices },
        { "triangles", p.triangles }, { "goal", p.goal }, { "triangles_after", p.trianglesAfter },
        { "active_vertices", p.activeVertices }, { "edges_placed", p.edgesPlaced },
        { "candidates", p.candidates }, { "collapses", p.collapses }, { "illegal", p.illegal },
        { "steps", steps }, { "mode", storage::ToString(p.mode) } });
    }
    j["passes"] = passes;
    const auto& s = stats.storage;
    j["storage"] = { { "mode", storage::ToString(s.mode) }, { "used_in_core", s.usedInCore },
      { "used_out_of_core", s.usedOutOfCore }, { "peak_bytes", s.peakBytes }, { "hits", s.hits },
      { "misses", s.misses }, { "bytes_read", s.bytesRead }, { "bytes_written", s.bytesWritten },
      { "reconfigurations", s.reconfigurations }, { "forks", s.forks },
      { "peak_file_bytes", s.peakFileBytes }, { "declared_bytes", s.declaredBytes },
      { "notes", s.notes } };
    statsFile.emplace(a.statsJson, j.dump(2) + "\n");
  }
  sink.Commit();
  for (auto& s : lodSinks)
  {
    s->Commit();
  }
  if (statsFile)
  {
    statsFile->Commit();
  }

  for (const std::string& note : stats.storage.notes)
  {
    // e.g. a full temporary directory and where the block files went: even with --quiet
    std::fprintf(stderr, "sipmss: warning: %s\n", note.c_str());
  }
  for (const std::string& warning : stats.warnings)
  {
    std::fprintf(stderr, "sipmss: warning: %s\n", warning.c_str());
  }
  if (stats.droppedInputFaces)
  {
    // a repair of the input is reported even with --quiet
    std::fprintf(stderr,
      "sipmss: warning: %s: dropped %llu degenerate faces (fewer than 3 distinct vertices, zero "
      "area, or the same vertices as another face)\n",
      a.input.c_str(), (unsigned long long)stats.droppedInputFaces);
  }
  if (!a.quiet)
  {
    char disk[64] = "";
    if (stats.storage.usedOutOfCore)
    {
      std::snprintf(disk, sizeof(disk), " (temporary files: %.1f MB at most)",
        double(stats.storage.peakFileBytes) / 1e6);
    }
    char error[64] = "";
    if (stats.achievedError >= 0)
    {
      std::snprintf(error, sizeof(error), ", error %.3g of the diagonal", stats.achievedError);
    }
    std::string algorithm = a.algorithm;
    if (stats.gridDimension > 0)
    {
      algorithm += " (grid " + std::to_string(stats.gridDimension) + ")";
    }
    else if (a.algorithm == "two-stage")
    {
      algorithm += " (stage 1 skipped: its grid would keep most of the input)";
    }
    std::printf("sipmss: %s %s: %llu -> %llu triangles (%llu vertices%s) in %.2f s, peak RSS "
                "%.1f MB, %s%s\n",
      algorithm.c_str(), a.input.c_str(), (unsigned long long)stats.inputTriangles,
      (unsigned long long)stats.outputTriangles, (unsigned long long)stats.outputVertices, error,
      seconds,
      PeakRssMB(),
      stats.storage.usedOutOfCore ? (stats.storage.usedInCore ? "out of core then in core" : "out of core")
                                  : "in core",
      disk);
    if (request.pruneSize > 0)
    {
      std::printf("sipmss: pruned %llu disconnected pieces (%llu triangles)\n",
        (unsigned long long)stats.prunedComponents, (unsigned long long)stats.prunedTriangles);
    }
    std::printf("sipmss: wrote %s\n", a.output.c_str());
    if (request.levelsOfDetail > 1 && !lodSinks.empty())
    {
      std::printf("sipmss: wrote %zu levels of detail %s .. %s\n", lodSinks.size(),
        LodPath(a.output, 0).c_str(), LodPath(a.output, int(lodSinks.size()) - 1).c_str());
    }
  }
  return 0;
}

// Collects a mesh for compare, with the values of the attribute channels `names` asks for
// (algorithms::AttributeChannels' names, unweighted: colors from 0 to 1) per vertex, and the
// groups (first channel, count) of each name.
class CompareSink final : public io::MeshSink
{
public:
  CompareSink(algorithms::TriangleMesh& mesh, const std::vector<algorithms::AttributeWeight>& names,
    const std::string& path)
    : mesh_(mesh)
    , positions_(mesh.points, mesh.triangles)
    , names_(names)
    , path_(path)
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->layout_ = h.layout;
    try
    {
      this->channels_ = algorithms::AttributeChannels(h.layout, this->names_);
    }
    catch (const algorithms::MissingArrayError& e)
    {
      throw algorithms::MissingArrayError(this->path_ + ": " + e.what());
    }
    this->groups.clear();
    std::size_t first = 0;
    for (const auto& n : this->names_)
    {
      // (the channels of each name, in order: AttributeChannels)
      const std::size_t count = algorithms::AttributeChannels(h.layout, { n }).size();
      this->groups.push_back({ first, count });
      first += count;
    }
    this->mesh_.attributeStride = this->channels_.size();
    this->positions_.Begin(h);
  }
  void Vertices(const io::VertexChunk& c) override
  {
    this->positions_.Vertices(c);
    const std::size_t k = this->channels_.size();
    if (k == 0)
    {
      return;
    }
    std::vector<std::uint8_t> rec(algorithms::RecordSize(this->layout_));
    std::vector<float>& out = this->mesh_.attributes;
    out.resize(std::max(out.size(), k * (c.first + c.count)));
    for (std::size_t i = 0; i < c.count; ++i)
    {
      algorithms::PackRecord(this->layout_, c, i, rec.data());
      for (std::size_t j = 0; j < k; ++j)
      {
        out[k * (c.first + i) + j] = float(algorithms::ChannelValue(this->channels_[j], rec.data()));
      }
    }
  }
  void Triangles(const std::uint32_t* indices, std::size_t count) override
  {
    this->positions_.Triangles(indices, count);
  }
  void End(const io::ReadStats& s) override { this->positions_.End(s); }
  std::vector<std::array<std::size_t, 2>> groups;

private:
  algorithms::TriangleMesh& mesh_;
  io::VectorSink positions_;
  const std::vector<algorithms::AttributeWeight>& names_;
  std::string path_;
  io::VertexLayout layout_;
  std::vector<algorithms::AttributeChannel> channels_;
};

int RunCompare(const std::string& ref, const std::string& cand, std::uint64_t samples,
  const std::string& attributes)
{
  std::vector<algorithms::AttributeWeight> names;
  const std::string problem = algorithms::ParseAttributeWeights(attributes, names);
  if (!problem.empty())
  {
    throw CLI::ValidationError("--attributes", problem);
  }
  for (algorithms::AttributeWeight& n : names)
  {
    n.weight = 1.0; // (compare measures the attributes as they are)
  }
  algorithms::TriangleMesh a, b;
  CompareSink sa(a, names, ref), sb(b, names, cand);
  io::ReadMesh(ref, sa);
  io::ReadMesh(cand, sb);
  for (const auto& [path, mesh] : { std::pair<const std::string&, const algorithms::TriangleMesh&>(
                                      ref, a), { cand, b } })
  {
    if (mesh.NumberOfTriangles() == 0)
    {
      throw io::MeshIOError(path + ": nothing to compare: the input has no valid triangle");
    }
  }
  for (std::size_t g = 0; g < names.size(); ++g)
  {
    if (sa.groups[g] != sb.groups[g])
    {
      throw io::MeshIOError(cand + ": its attribute '" + names[g].name + "' has " +
        std::to_string(sb.groups[g][1]) + " components, " + ref + "'s has " +
        std::to_string(sa.groups[g][1]));
    }
  }
  algorithms::CompareOptions o;
  o.samples = samples;
  o.attributeGroups = sa.groups;
  const algorithms::CompareResult r = algorithms::CompareMeshes(a, b, o);
  nlohmann::json j = { { "mean", r.mean }, { "rms", r.rms }, { "hausdorff", r.hausdorff },
    { "diagonal", r.diagonal }, { "samples", r.samples }, { "mean_absolute", r.meanAbsolute },
    { "rms_absolute", r.rmsAbsolute }, { "hausdorff_absolute", r.hausdorffAbsolute },
    { "reference_triangles", a.NumberOfTriangles() },
    { "candidate_triangles", b.NumberOfTriangles() } };
  if (!names.empty())
  {
    nlohmann::json at = nlohmann::json::object();
    for (std::size_t g = 0; g < names.size(); ++g)
    {
      at[names[g].name] = { { "rms", r.attributeRms[g] }, { "max", r.attributeMax[g] },
        { "components", sa.groups[g][1] } };
    }
    j["attributes"] = at;
  }
  std::printf("%s\n", j.dump(2).c_str());
  return 0;
}

int RunInfo(const std::string& path)
{
  InfoSink s;
  io::ReadMesh(path, s);
  if (s.stats.triangles == 0)
  {
    // the file is valid and described below, but simplify would refuse it: say so in its words
    std::fprintf(stderr, "sipmss: warning: %s: nothing to simplify: the input has no valid triangle%s\n",
      path.c_str(),
      s.stats.droppedFaces
        ? (" (" + std::to_string(s.stats.droppedFaces) + " degenerate faces were dropped)").c_str()
        : "");
  }
  nlohmann::json j = { { "file", path }, { "format", io::ToString(s.header.format) },
    { "vertices", s.stats.vertices }, { "faces", s.stats.polygons },
    { "triangles", s.stats.triangles }, { "dropped_faces", s.stats.droppedFaces },
    { "bounds", s.stats.vertices ? nlohmann::json(s.bounds) : nlohmann::json(nullptr) } };
  nlohmann::json props = nlohmann::json::array();
  if (s.header.layout.normals)
    props.push_back("normals");
  if (s.header.layout.colors)
    props.push_back("colors");
  if (s.header.layout.texcoords)
    props.push_back("texcoords");
  for (const auto& n : s.header.layout.scalars)
    props.push_back(n);
  j["vertex_properties"] = props;
  // (the names --selection-array can take as a face property)
  j["face_properties"] = s.header.faceScalars;
  std::printf("%s\n", j.dump(2).c_str());
  return 0;
}

} // namespace

int main(int argc, char** argv)
{
  // Under a limit on the address space (ulimit -v), every thread's first allocation would reserve
  // a glibc arena of 64 MiB of it, which the automatic budget cannot foresee: one arena for all
  // threads then (the threads allocate little; their scratch is reused).
  {
    struct rlimit rl{};
    if (::getrlimit(RLIMIT_AS, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY)
    {
      ::mallopt(M_ARENA_MAX, 1);
    }
  }
  CLI::App app{ "sipmss: simplify huge triangle meshes under a fixed memory budget" };
  app.set_version_flag("--version", std::string("sipmss ") + SIPMSS_VERSION);
  app.require_subcommand(1);

  SimplifyArgs sa;
  algorithms::SimplifyRequest& rq = sa.request;
  std::int64_t target = 0;
  CLI::App* simplify = app.add_subcommand("simplify", "simplify INPUT into OUTPUT");
  simplify->add_option("INPUT", sa.input, "PLY, STL or OBJ file (.gz too)")->required();
  simplify->add_option("OUTPUT", sa.output,
    "output file (.ply, .stl or .obj, optionally .gz); never the input file")->required();
  simplify->add_option("--algorithm", sa.algorithm, "cluster (default), decimate or two-stage")
    ->check(CLI::IsMember({ "cluster", "decimate", "two-stage" }));
  // The options, grouped by topic, are those of the filters (docs/architecture.md, "One
  // request"); their ranges and messages are algorithms::Problems', checked once parsed.
  CLI::Option_group* targets = simplify->add_option_group("Target",
    "decimate and two-stage: how far to simplify");
  auto* targetOption = targets->add_option("--target", target,
    "stop at this many triangles (at least 1)");
  auto* reduction = targets->add_option("--reduction", rq.targetReduction,
    "fraction of the triangles to remove (default 0.9 without --target and --max-error)")
    ->excludes(targetOption);
  auto* maxError = targets->add_option("--max-error", rq.maximumError,
    "an error bound: no collapse whose error (the RMS distance of the merged vertex to the "
    "input's planes it stands for) exceeds this fraction of the input's bounding-box diagonal "
    "(default: no bound); without --target the run goes as far as the bound allows");
  auto* absoluteError = targets->add_flag("--absolute-error", rq.absoluteError,
    "--max-error is a distance in the input's units, not a fraction of the diagonal");
  auto* lods = targets->add_option("--lods", rq.levelsOfDetail,
    "levels of detail, written as OUTPUT_lodK, finest first (default 1); spaced evenly in log(triangles) "
    "down to the target, or with --max-error and no --target each one stopping at half of the next "
    "one's bound");
  CLI::Option_group* clustering = simplify->add_option_group("Clustering",
    "cluster and two-stage: the grid");
  auto* grid = clustering->add_option("--grid", rq.grid,
    "maximum grid dimension (cells along the longest axis; cluster: default 50; two-stage: "
    "default 300, or with a --target T above 19125 the grid whose clustered mesh has about 16 T "
    "triangles, ceil(sqrt(16 T / 3.4)), e.g. 686 for 100000; when that grid would keep at least 0.7 "
    "of the input's triangles, stage 1 is skipped)");
  auto* bounds = clustering->add_option("--bounds", sa.bounds,
    "cluster: the grid's box, xmin xmax ymin ymax zmin zmax (default: the input's bounds)")
    ->expected(6)
    ->allow_extra_args(false);
  CLI::Option_group* boundaries = simplify->add_option_group("Boundaries, locks and welding");
  boundaries->add_option("--boundary-weight", rq.boundaryWeight,
    "weight of the boundary quadrics that keep holes in place (cluster: default 0 = off, slower "
    "when on; decimate, two-stage: default 100)");
  auto* lockBoundary = boundaries->add_flag("--lock-boundary", rq.lockBoundary,
    "decimate, two-stage: boundary vertices never move");
  auto* noFit = boundaries->add_flag_function("--no-fit",
    [&rq](std::int64_t) { rq.fitSurface = false; },
    "decimate, two-stage: keep the merged vertices at the quadrics' positions (default: a final "
    "fit moves each along its normal so that the faces pass through a sample of the input's "
    "vertices in the least-squares sense, never above the largest error of a vertex)");
  auto* weld = boundaries->add_option("--weld", rq.weldDistance,
    "decimate, two-stage: weld input vertices closer than this distance first (default: off)");
  auto* lockArray = boundaries->add_option("--lock-array", rq.lockArray,
    "decimate: a vertex property (point array) of INPUT; vertices where it is not 0 stay in the "
    "output at their exact positions (not with --weld)");
  auto* selectionArray = boundaries->add_option("--selection-array", rq.selectionArray,
    "decimate: a vertex property (point array) of INPUT, only vertices where it is not 0 move "
    "or go, faces without one are kept as they were; or a face property (cell array), every "
    "face where it is 0 is kept as it was");
  CLI::Option_group* cleanup = simplify->add_option_group("Cleanup");
  auto* pruneSize = cleanup->add_option("--prune-size", rq.pruneSize,
    "decimate, two-stage: first remove disconnected pieces whose bounding-box diagonal is below "
    "this fraction of the input's (e.g. 0.01; default 0: keep every piece); a piece with a "
    "vertex that --lock-array or --selection-array keeps stays");
  CLI::Option_group* attributes = simplify->add_option_group("Attributes");
  attributes->add_option("--attributes", rq.attributes,
    "point attributes that join the error, NAME[:WEIGHT],... (weight default 1): a vertex "
    "property of INPUT, or normals, colors (or rgb, rgba), texcoords (or uv); e.g. "
    "normals:0.5,colors:1. A weight of 1 makes a change of 1 in the attribute (colors from 0 to "
    "1) across a distance d cost about as much as moving the surface by d (meshoptimizer's "
    "weighting); merged vertices take the attributes' optimal values (default: geometry only)");
  CLI::Option_group* storageGroup = simplify->add_option_group("Memory and storage");
  storageGroup->add_option("--memory-mb", sa.memory,
    "memory budget in MiB (at least 0.0625), auto (= 0, the default: half of what this process "
    "may use: the lowest of the cgroup limit, ulimit -v/-d and MemAvailable) or unbounded "
    "(= -1: always in core)")
    ->capture_default_str();
  // One directory per --tmpdir (repeat it for more): a list option would also swallow the
  // positionals after it (`--tmpdir /scratch in.ply out.ply`).
  storageGroup->add_option("--tmpdir", rq.temporaryDirectories,
    "directory for out-of-core files (repeatable; one that is missing, read-only or full is "
    "skipped)")
    ->expected(1)
    ->allow_extra_args(false)
    ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
  storageGroup->add_option("--mode", sa.mode,
    "auto (default: in core when the data fits the budget), in-core or out-of-core")
    ->check(CLI::IsMember({ "auto", "in-core", "out-of-core" }))
    ->capture_default_str();
  storageGroup->add_option("--threads", rq.threads,
    "threads (0 = all cores, the default; the output does not depend on it)");
  CLI::Option_group* report = simplify->add_option_group("Output");
  report->add_option("--stats-json", sa.statsJson, "write run statistics as JSON");
  report->add_flag("--quiet", sa.quiet, "no progress bar and no summary");
  // Once parsed: the request is complete, an option that does not apply to the chosen algorithm
  // is a usage error (not ignored), and the request's own rules hold.
  simplify->callback([&]() {
    rq.algorithm = sa.algorithm == "decimate" ? algorithms::Algorithm::Decimate
      : sa.algorithm == "two-stage"           ? algorithms::Algorithm::TwoStage
                                              : algorithms::Algorithm::Cluster;
    const bool cluster = rq.algorithm == algorithms::Algorithm::Cluster;
    const std::pair<CLI::Option*, bool> applies[] = {
      { grid, rq.algorithm != algorithms::Algorithm::Decimate }, { bounds, cluster },
      { targetOption, !cluster }, { reduction, !cluster }, { maxError, !cluster },
      { absoluteError, !cluster }, { pruneSize, !cluster },
      { lods, !cluster }, { lockBoundary, !cluster }, { noFit, !cluster }, { weld, !cluster },
      { lockArray, rq.algorithm == algorithms::Algorithm::Decimate },
      { selectionArray, rq.algorithm == algorithms::Algorithm::Decimate } };
    for (const auto& [option, ok] : applies)
    {
      if (option->count() > 0 && !ok)
      {
        throw CLI::ValidationError(option->get_name(),
          "does not apply to --algorithm " + sa.algorithm + " (see sipmss simplify --help)");
      }
    }
    if (targetOption->count() > 0 && target < 1)
    {
      throw CLI::ValidationError("--target", "must be at least 1, not " + std::to_string(target));
    }
    rq.targetTriangles = static_cast<std::uint64_t>(std::max<std::int64_t>(target, 0));
    if (absoluteError->count() > 0 && maxError->count() == 0)
    {
      throw CLI::ValidationError("--absolute-error", "needs --max-error (it says how to read it)");
    }
    if (reduction->count() > 0 && maxError->count() > 0 && std::isfinite(rq.maximumError))
    {
      // (the filters' TargetReduction is likewise unused with a bound and no target)
      throw CLI::ValidationError("--reduction",
        "has no effect with --max-error: without --target the bound is the only stop (give "
        "--target for a triangle count too)");
    }
    if (grid->count() > 0 && rq.grid < 1)
    {
      throw CLI::ValidationError("--grid", "must be at least 1, not " + std::to_string(rq.grid));
    }
    if (!sa.bounds.empty())
    {
      rq.bounds.emplace();
      std::copy_n(sa.bounds.begin(), 6, rq.bounds->begin());
    }
    if (!algorithms::ParseMemoryBudget(sa.memory, rq.memoryBudgetMB))
    {
      throw CLI::ValidationError(
        "--memory-mb", "must be auto, unbounded or a number of MiB, not " + sa.memory);
    }
    rq.mode = sa.mode == "in-core" ? storage::ModePolicy::InCore
      : sa.mode == "out-of-core"   ? storage::ModePolicy::OutOfCore
                                   : storage::ModePolicy::Automatic;
    for (const auto& p : algorithms::Problems(rq))
    {
      throw CLI::ValidationError(algorithms::CliOption(p.parameter), p.problem);
    }
  });

  std::string ref, cand;
  std::uint64_t samples = 0;
  CLI::App* compare = app.add_subcommand("compare", "Metro-style distance between two meshes");
  compare->add_option("REFERENCE", ref)->required();
  compare->add_option("CANDIDATE", cand)->required();
  compare->add_option("--samples", samples, "samples per side (default: automatic)")
    ->check(CLI::Range(std::uint64_t(0), std::uint64_t(1) << 40));
  std::string compareAttributes;
  compare->add_option("--attributes", compareAttributes,
    "also compare these point attributes (names as simplify --attributes takes them; weights are "
    "ignored): interpolated at each sample and at its nearest point on the other mesh, the RMS "
    "and largest difference (colors from 0 to 1)");

  std::string infoPath;
  CLI::App* info = app.add_subcommand("info", "format, counts and bounds of a mesh file");
  info->add_option("FILE", infoPath)->required();

  try
  {
    app.parse(argc, argv);
  }
  catch (const CLI::ParseError& e)
  {
    const int rc = app.exit(e);
    return rc == 0 ? 0 : 2;
  }

  const bool readOnly = !*simplify;
  std::signal(SIGINT, readOnly ? OnInterruptReadOnly : OnInterrupt);
  std::signal(SIGTERM, readOnly ? OnInterruptReadOnly : OnInterrupt);
  try
  {
    if (*simplify)
    {
      return RunSimplify(sa);
    }
    if (*compare)
    {
      return RunCompare(ref, cand, samples, compareAttributes);
    }
    return RunInfo(infoPath);
  }
  catch (const algorithms::AbortedError&)
  {
    std::fprintf(stderr, "sipmss: interrupted; nothing was written\n");
    return 128 + (g_interrupted ? int(g_interrupted) : SIGINT);
  }
  catch (const CLI::ValidationError& e)
  {
    std::fprintf(stderr, "sipmss: error: %s\n", e.what());
    return 2;
  }
  catch (const std::bad_alloc&)
  {
    // (the cores name their phase and budget themselves: OutOfMemoryError)
    std::fprintf(stderr,
      "sipmss: error: out of memory: set a smaller budget (--memory-mb) so that more of the run "
      "goes to disk, or free memory\n");
    return 1;
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss: error: %s\n", e.what());
    return 1;
  }
}
