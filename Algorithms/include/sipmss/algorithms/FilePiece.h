// This rank's piece of a file read by byte ranges (io/MeshPiece.h), for the distributed runs:
// rank r of N reads faces [F r / N, F (r + 1) / N) and the vertex records they use, never the
// whole file (docs/architecture.md, "Reading a file in pieces").
#pragma once

#include "sipmss/algorithms/Common.h"
#include "sipmss/algorithms/Communicator.h"
#include "sipmss/algorithms/Simplify.h"
#include "sipmss/storage/DML.h"

#include <memory>
#include <string>

namespace sipmss::algorithms
{

// The profile of the piece's DML for a run of `request`: an eighth of its budget (at least
// 64 KiB; unbounded stays unbounded), set aside in request.reservedMemoryBytes so that the run
// gets the rest.
storage::Profile ReservePieceBudget(SimplifyRequest& request);

class FilePiece
{
public:
  // Collective: every rank of `comm` constructs it with the same path. Binary PLY: reads this
  // rank's faces, then lists the vertex numbers they use (through a dense map over the range of
  // numbers they use) and renumbers the faces, in a DML of its own configured with `profile`.
  // Binary STL: reads nothing yet.
  // A file that cannot be read in pieces (ASCII, OBJ, gzip, faces that are not all triangles, or
  // one that a rank other than 0 cannot open) gives Split() false on every rank: rank 0 reads it
  // whole, once, and sends every rank the same piece (Scattered() true): its share of the faces
  // and the vertices they use, in bounded rounds, kept in this DML (rank 0 holds the whole mesh
  // in a DML of its own, with the same profile, until the pieces are sent). Any failure on any
  // rank (rank 0 cannot open or read it, a bad index, an abort) throws on every rank: the
  // failing rank its own error, the others one that names it.
  FilePiece(const std::string& path, Communicator& comm, const storage::Profile& profile,
    Progress& progress);
  ~FilePiece();
  FilePiece(const FilePiece&) = delete;
  FilePiece& operator=(const FilePiece&) = delete;

  bool Split() const;     // read by byte ranges
  bool Scattered() const; // read by rank 0 and sent
  const std::string& WhyNot() const; // (Split() false)
  // The scatter's exchanges (none when Split()).
  const CommunicationStats& Traffic() const;
  // Replays this rank's piece as a mesh of its own (valid while this object lives).
  MeshSource Source();
  // Bytes of the file this rank has read: the faces once, the vertex records at every replay;
  // scattered: the whole file on rank 0 (uncompressed), nothing elsewhere.
  std::uint64_t BytesRead() const;
  std::uint64_t FileBytes() const;
  std::uint64_t Faces() const; // the file's faces (facets) this piece holds

private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

} // namespace sipmss::algorithms
