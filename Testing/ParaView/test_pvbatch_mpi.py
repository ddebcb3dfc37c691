"""mpirun -np N pvbatch: the SIPMSS filters on a mesh distributed over N ranks.

- SIPMSS Cluster on the pieces (the source's, and RedistributeDataSet's) gives the serial result: the triangles
  of all ranks together are the `sipmss` CLI's on the whole mesh, the same set at the same
  coordinates, none twice; every rank reports its traffic.
- SIPMSS Cluster File under MPI is run by rank 0 alone: the file once, not N copies.
- SIPMSS Decimate on the pieces, also as two-stage (PreClusterGridDimension), has no seams: as
  many boundary edges as the CLI's serial run on the whole mesh, no face twice, the target within
  1% and the RMS distance within 1.1 times the serial run's.
"""
import json
import os
import struct
import subprocess
import sys
import tempfile

from paraview import servermanager
from paraview.simple import *  # noqa: F401,F403
from vtkmodules.vtkFiltersCore import vtkCleanPolyData
from vtkmodules.vtkIOPLY import vtkPLYWriter

LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=True, ns=globals())

pm = servermanager.vtkProcessModule.GetProcessModule()
ranks = pm.GetNumberOfLocalPartitions()
expected_ranks = int(os.environ.get("SIPMSS_RANKS", "2"))
assert ranks == expected_ranks, "expected %d MPI ranks, got %d" % (expected_ranks, ranks)
GRID = 23


def read_ply(path):
    """Triangles of a binary little-endian PLY (float xyz, uchar/int lists) by coordinates."""
    with open(path, "rb") as f:
        header = b""
        while not header.endswith(b"end_header\n"):
            header += f.readline()
        lines = header.decode().splitlines()
        nv = int(next(l for l in lines if l.startswith("element vertex")).split()[2])
        nf = int(next(l for l in lines if l.startswith("element face")).split()[2])
        props = [l.split() for l in lines if l.startswith("property")]
        vprops = props[: next(i for i, p in enumerate(props) if p[1] == "list")]
        sizes = {"float": 4, "float32": 4, "uchar": 1, "uint8": 1, "int": 4, "int32": 4,
                 "double": 8, "float64": 8, "short": 2, "ushort": 2, "uint": 4, "uint32": 4}
        stride = sum(sizes[p[1]] for p in vprops)
        data = f.read(nv * stride)
        points = [struct.unpack_from("<3f", data, i * stride) for i in range(nv)]
        tris = []
        for _ in range(nf):
            (n,) = struct.unpack("<B", f.read(1))
            tris.append(struct.unpack("<%di" % n, f.read(4 * n)))
    return canonical(points, tris)


def canonical(points, tris):
    out = []
    for t in tris:
        c = [tuple(points[i]) for i in t]
        m = c.index(min(c))
        out.append(tuple(c[m:] + c[:m]))
    return sorted(out)


def boundary_edges(tris):
    """Edges (by their end points' coordinates) used by one triangle."""
    uses = {}
    for t in tris:
        for k in range(3):
            e = tuple(sorted((t[k], t[(k + 1) % 3])))
            uses[e] = uses.get(e, 0) + 1
    return sum(1 for n in uses.values() if n == 1)


def rms_of(reference, candidate):
    out = subprocess.run([os.environ["SIPMSS_CLI"], "compare", reference, candidate],
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out)["rms"]


def triangles_of(poly):
    pts = poly.GetPoints()
    points = [pts.GetPoint(i) for i in range(poly.GetNumberOfPoints())] if pts else []
    # (float32 in the filter's output: the doubles GetPoint returns are those floats)
    points = [tuple(struct.unpack("<3f", struct.pack("<3f", *p))) for p in points]
    tris = []
    ids = poly.GetPolys()
    ids.InitTraversal()
    from vtkmodules.vtkCommonCore import vtkIdList
    l = vtkIdList()
    while ids.GetNextCell(l):
        tris.append(tuple(l.GetId(k) for k in range(l.GetNumberOfIds())))
    return canonical(points, tris)


sphere = Sphere(ThetaResolution=160, PhiResolution=120)
# The pieces: the sphere source's own (it makes piece r of N on rank r), and RedistributeDataSet's
# partition of them when it works here (its exchange goes through VTK's XML readers, which fail
# with this machine's libexpat: then its pieces lose cells and that input is skipped).
surface = ExtractSurface(Input=sphere)
inputs = [("the source's pieces", surface)]
if "RedistributeDataSet" in globals() and ranks > 1:
    redistributed = ExtractSurface(Input=RedistributeDataSet(Input=sphere))
    inputs.append(("RedistributeDataSet's pieces", redistributed))

# The serial reference: the whole mesh as a PLY file through the CLI.
whole = servermanager.Fetch(sphere)
tmp = tempfile.mkdtemp(prefix="sipmss-mpi-")
try:
    mesh = os.path.join(tmp, "sphere.ply")
    writer = vtkPLYWriter()
    writer.SetInputData(whole)
    writer.SetFileName(mesh)
    writer.SetFileTypeToBinary()
    assert writer.Write() == 1
    serial_out = os.path.join(tmp, "serial.ply")
    subprocess.run([os.environ["SIPMSS_CLI"], "simplify", mesh, serial_out, "--algorithm",
                    "cluster", "--grid", str(GRID), "--quiet"], check=True)
    serial = read_ply(serial_out)
    assert len(serial) > 500, len(serial)

    whole_triangles = triangles_of(whole)
    for name, pieces in inputs:
        if triangles_of(servermanager.Fetch(pieces)) != whole_triangles:
            print("skipped: %s are not the whole sphere on this machine" % name)
            continue
        # Cluster on the distributed pieces.
        cluster = SIPMSSCluster(Input=pieces)
        cluster.MaximumGridDimension = GRID
        cluster.NumberOfThreads = 1  # (the ranks share the cores)
        cluster.UpdatePipeline()
        distributed = triangles_of(servermanager.Fetch(cluster))
        assert distributed == serial, (
            "%s, %d ranks: %d triangles, serial %d; %d not in the serial result, %d missing" % (
                name, ranks, len(distributed), len(serial),
                len(set(distributed) - set(serial)), len(set(serial) - set(distributed))))
        assert len(set(distributed)) == len(distributed), "a triangle twice"
        cluster.UpdatePropertyInformation()
        n_ranks = cluster.GetProperty("NumberOfRanks").GetData()
        stats = cluster.GetProperty("RankStatistics").GetData()
        if ranks > 1:
            assert n_ranks == ranks, (n_ranks, ranks)
            for r in range(ranks):
                assert ("rank %d:" % r) in stats, stats
            assert cluster.GetProperty("BytesSent").GetData() > 0
            print("%s, per rank: %s" % (name, stats))
        else:
            assert n_ranks == 1 and stats == "", (n_ranks, stats)
        print("%s: the union of %d ranks' outputs is the serial result (%d triangles)" % (
            name, ranks, len(serial)))

    # The File source: one copy of the result, whatever the number of ranks.
    cluster_file = SIPMSSClusterFile(FileName=mesh)
    cluster_file.MaximumGridDimension = GRID
    cluster_file.UpdatePipeline()
    from_file = triangles_of(servermanager.Fetch(cluster_file))
    assert from_file == serial, (len(from_file), len(serial))

    # Decimate on the distributed pieces: each rank's piece with its border locked, then the
    # joined results on rank 0. Against the CLI's serial run: no seam (as many boundary edges),
    # no face twice, the target within 1%, the RMS distance within 1.1x.
    # (the serial input is the whole sphere with the points the pieces share merged: the
    # appended pieces repeat them, which a serial run would take for cuts. The source's pieces
    # leave a slit along one meridian, its two sides 1e-16 apart: both runs lock the boundary,
    # so that the boundary edges are the input's in both, and a seam left open would add some.)
    TARGET = 2000
    clean = vtkCleanPolyData()
    clean.SetInputData(whole)
    clean.Update()
    merged = os.path.join(tmp, "merged.ply")
    writer = vtkPLYWriter()
    writer.SetInputData(clean.GetOutput())
    writer.SetFileName(merged)
    writer.SetFileTypeToBinary()
    assert writer.Write() == 1
    # Two-stage: the distributed clustering at PRE_GRID, then the distributed decimation.
    PRE_GRID = 60
    for algorithm, grid_args in (("decimate", []), ("two-stage", ["--grid", str(PRE_GRID)])):
        serial_dec = os.path.join(tmp, "serial-%s.ply" % algorithm)
        subprocess.run([os.environ["SIPMSS_CLI"], "simplify", merged, serial_dec, "--algorithm",
                        algorithm, "--target", str(TARGET), "--lock-boundary", "--quiet"]
                       + grid_args, check=True)
        serial_tris = read_ply(serial_dec)
        serial_rms = rms_of(merged, serial_dec)
        for name, pieces in inputs:
            if triangles_of(servermanager.Fetch(pieces)) != whole_triangles:
                continue  # (said above)
            name = "%s, %s" % (algorithm, name)
            decimate = SIPMSSDecimate(Input=pieces)
            decimate.TargetNumberOfTriangles = TARGET
            decimate.LockBoundary = 1
            decimate.NumberOfThreads = 1
            if grid_args:
                decimate.PreClusterGridDimension = PRE_GRID
            decimate.UpdatePipeline()
            result = servermanager.Fetch(decimate)
            tris = triangles_of(result)
            assert abs(len(tris) - TARGET) <= 0.01 * TARGET, (name, len(tris), TARGET)
            assert len(set(tris)) == len(tris), "%s: a face twice" % name
            assert boundary_edges(tris) == boundary_edges(serial_tris), (
                "%s, %d ranks: %d boundary edges, serial %d" % (
                    name, ranks, boundary_edges(tris), boundary_edges(serial_tris)))
            out = os.path.join(tmp, "distributed-decimate.ply")
            writer = vtkPLYWriter()
            writer.SetInputData(result)
            writer.SetFileName(out)
            writer.SetFileTypeToBinary()
            assert writer.Write() == 1
            rms = rms_of(merged, out)
            assert rms <= 1.1 * serial_rms, (name, ranks, rms, serial_rms)
            decimate.UpdatePropertyInformation()
            assert decimate.GetProperty("NumberOfRanks").GetData() == ranks
            if ranks > 1:
                assert decimate.GetProperty("BytesSent").GetData() > 0
            print("%s, %d ranks: %d triangles (serial %d), %d boundary edges, RMS %.4g "
                  "(serial %.4g, ratio %.3f)" % (name, ranks, len(tris), len(serial_tris),
                                                  boundary_edges(tris), rms, serial_rms,
                                                  rms / serial_rms))
finally:
    for name in os.listdir(tmp):
        os.remove(os.path.join(tmp, name))
    os.rmdir(tmp)
sys.stdout.flush()
