"""One request, two front ends: every property of the VTK filters has a `sipmss simplify` option
with the same default and the same effect.

Each case runs the filter (FileName, so both read the same file) and the CLI with the matching
option, and compares the two outputs exactly (points and triangles). Each case that changes the
result also differs from the default run, so an option or a property that were ignored would
fail. Storage and thread settings do not change the result: those cases check the statistics.
"""
import json
import os
import random
import subprocess
import sys
import tempfile
import unittest

from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkIOPLY import vtkPLYReader
from vtkmodules.util.numpy_support import vtk_to_numpy

from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate

CLI = os.environ.get("SIPMSS_CLI")


def sheet_with_a_seam(n=48, seed=3):
    """A bumpy open n x n grid (boundary all round) whose middle column is doubled: the two
    halves share positions but not vertices, until they are welded."""
    rng = random.Random(seed)
    noise = [[0.01 * rng.random() for _ in range(n)] for _ in range(n)]
    pts, ids = vtkPoints(), {}
    half = n // 2
    for side in (0, 1):
        cols = range(0, half + 1) if side == 0 else range(half, n)
        for j in range(n):
            for i in cols:
                z = 0.05 * ((i * 7 + j * 13) % 5) / 5.0 + noise[j][i]
                ids[(side, i, j)] = pts.InsertNextPoint(i / (n - 1.0), j / (n - 1.0), z)
    cells = vtkCellArray()
    for j in range(n - 1):
        for i in range(n - 1):
            side = 0 if i < half else 1
            a, b = ids[(side, i, j)], ids[(side, i + 1, j)]
            c, d = ids[(side, i + 1, j + 1)], ids[(side, i, j + 1)]
            cells.InsertNextCell(3, (a, b, c))
            cells.InsertNextCell(3, (a, c, d))
    pd = vtkPolyData()
    pd.SetPoints(pts)
    pd.SetPolys(cells)
    return pd


def write_ply(pd, path, point_arrays, face_arrays=None):
    """A binary PLY of pd's points and triangles with float vertex properties (vtkPLYWriter writes
    no other point arrays): point_arrays maps a name to a function of the point (x, y, z), and
    face_arrays (uchar face properties after the indices) one to a function of the face's
    centroid."""
    import struct
    face_arrays = face_arrays or {}
    pts = vtk_to_numpy(pd.GetPoints().GetData())
    conn = vtk_to_numpy(pd.GetPolys().GetConnectivityArray())
    names, face_names = sorted(point_arrays), sorted(face_arrays)
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\n"
                 "property float x\nproperty float y\nproperty float z\n" % len(pts)).encode())
        for name in names:
            f.write(("property float %s\n" % name).encode())
        f.write(("element face %d\nproperty list uchar int vertex_indices\n" % (len(conn) // 3)).encode())
        for name in face_names:
            f.write(("property uchar %s\n" % name).encode())
        f.write(b"end_header\n")
        for p in pts:
            values = [float(p[0]), float(p[1]), float(p[2])] + [float(point_arrays[n](*p)) for n in names]
            f.write(struct.pack("<%df" % len(values), *values))
        for t in range(len(conn) // 3):
            ids = [int(i) for i in conn[3 * t:3 * t + 3]]
            c = [sum(float(pts[i][k]) for i in ids) / 3 for k in range(3)]
            f.write(struct.pack("<B3i", 3, *ids))
            for name in face_names:
                f.write(struct.pack("<B", int(face_arrays[name](*c))))


def arrays(pd):
    return (vtk_to_numpy(pd.GetPoints().GetData()).astype("float64"),
            vtk_to_numpy(pd.GetPolys().GetConnectivityArray()).astype("int64"))


# (filter class, properties, CLI arguments, changes the result)
CASES = [
    (vtkSIPMSSCluster, {}, [], False),
    (vtkSIPMSSCluster, {"MaximumGridDimension": 12}, ["--grid", "12"], True),
    (vtkSIPMSSCluster, {"BoundaryWeight": 1.0}, ["--boundary-weight", "1"], True),
    (vtkSIPMSSCluster, {"UseBounds": True, "Bounds": (-0.5, 1.5, -0.5, 1.5, -0.5, 1.5)},
     ["--bounds", "-0.5", "1.5", "-0.5", "1.5", "-0.5", "1.5"], True),
    (vtkSIPMSSCluster, {"Attributes": "keep:1"}, ["--attributes", "keep:1"], True),
    (vtkSIPMSSCluster, {"NumberOfThreads": 1}, ["--threads", "1"], False),
    (vtkSIPMSSCluster, {"OperationMode": 2, "MemoryBudgetMB": 1.0},
     ["--mode", "out-of-core", "--memory-mb", "1"], False),
    (vtkSIPMSSDecimate, {}, [], False),
    (vtkSIPMSSDecimate, {"TargetNumberOfTriangles": 200}, ["--target", "200"], True),
    (vtkSIPMSSDecimate, {"TargetReduction": 0.5}, ["--reduction", "0.5"], True),
    (vtkSIPMSSDecimate, {"TargetNumberOfTriangles": 20, "MaximumError": 1e-3},
     ["--target", "20", "--max-error", "1e-3"], True),
    (vtkSIPMSSDecimate, {"MaximumError": 2e-3}, ["--max-error", "2e-3"], True),  # (no target)
    (vtkSIPMSSDecimate, {"MaximumError": 2e-3, "AbsoluteError": True},
     ["--max-error", "2e-3", "--absolute-error"], True),
    (vtkSIPMSSDecimate, {"NumberOfLevelsOfDetail": 3}, ["--lods", "3"], True),  # (the schedule)
    (vtkSIPMSSDecimate, {"LockBoundary": True}, ["--lock-boundary"], True),
    (vtkSIPMSSDecimate, {"FitSurface": False}, ["--no-fit"], True),
    (vtkSIPMSSDecimate, {"BoundaryWeight": 0.0}, ["--boundary-weight", "0"], True),
    (vtkSIPMSSDecimate, {"WeldDistance": 1e-6}, ["--weld", "1e-6"], True),
    (vtkSIPMSSDecimate, {"LockArray": "keep"}, ["--lock-array", "keep"], True),
    (vtkSIPMSSDecimate, {"SelectionArray": "region"}, ["--selection-array", "region"], True),
    (vtkSIPMSSDecimate, {"SelectionArray": "cells"}, ["--selection-array", "cells"], True),
    # (the two halves of the sheet are pieces of their own: the selected one is pruned)
    (vtkSIPMSSDecimate, {"SelectionArray": "region", "PruneSize": 0.9},
     ["--selection-array", "region", "--prune-size", "0.9"], True),
    (vtkSIPMSSDecimate, {"Attributes": "region:0.5,keep"}, ["--attributes", "region:0.5,keep"], True),
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": 30, "Attributes": "keep:2"},
     ["--algorithm", "two-stage", "--grid", "30", "--attributes", "keep:2"], True),
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": 30}, ["--algorithm", "two-stage", "--grid", "30"], True),
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": 300}, ["--algorithm", "two-stage"], True),
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": -1}, ["--algorithm", "two-stage"], True),
    # (the automatic grid with a target: max(300, ceil(sqrt(16 * 200 / 3.4))) = 300)
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": -1, "TargetNumberOfTriangles": 200},
     ["--algorithm", "two-stage", "--target", "200"], True),
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": 300, "TargetNumberOfTriangles": 200},
     ["--algorithm", "two-stage", "--target", "200"], True),
    # (grid 434, whose clustered mesh would keep more than 0.7 of the sheet: stage 1 skipped,
    # the decimation alone, as the CLI's; the target is above the sheet's 4,418 triangles)
    (vtkSIPMSSDecimate, {"PreClusterGridDimension": -1, "TargetNumberOfTriangles": 40000},
     ["--algorithm", "two-stage", "--target", "40000"], True),
    (vtkSIPMSSDecimate, {"NumberOfThreads": 1, "OperationMode": 1},
     ["--threads", "1", "--mode", "in-core"], False),
    (vtkSIPMSSDecimate, {"OperationMode": 2, "MemoryBudgetMB": 1.0},
     ["--mode", "out-of-core", "--memory-mb", "1"], False),
]


@unittest.skipUnless(CLI, "SIPMSS_CLI is not set (run through ctest)")
class FrontEnds(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.TemporaryDirectory()
        cls.input = os.path.join(cls.tmp.name, "sheet.ply")
        # (point arrays for the locks and the selection: a diagonal band, the right half)
        write_ply(sheet_with_a_seam(), cls.input,
                  {"keep": lambda x, y, z: 1.0 if abs(x - y) < 0.05 else 0.0,
                   "region": lambda x, y, z: 1.0 if x > 0.5 else 0.0},
                  {"cells": lambda x, y, z: 1 if y < 0.6 else 0})
        cls.defaults = {}

    @classmethod
    def tearDownClass(cls):
        cls.tmp.cleanup()

    def run_filter(self, cls, props):
        f = cls()
        f.SetFileName(self.input)
        for name, value in props.items():
            setter = getattr(f, "Set" + name)
            setter(*value) if isinstance(value, tuple) else setter(value)
        f.Update()
        self.assertGreater(f.GetOutput().GetNumberOfPolys(), 0, "%s %s" % (cls.__name__, props))
        return f

    def run_cli(self, cls, args):
        out = os.path.join(self.tmp.name, "out.ply")
        stats = os.path.join(self.tmp.name, "stats.json")
        algorithm = [] if "--algorithm" in args else \
            ["--algorithm", "cluster" if cls is vtkSIPMSSCluster else "decimate"]
        r = subprocess.run([CLI, "simplify", self.input, out, "--quiet", "--stats-json", stats] +
                           algorithm + args, capture_output=True, text=True)
        self.assertEqual(r.returncode, 0, "%s %s" % (args, r.stderr))
        reader = vtkPLYReader()
        reader.SetFileName(out)
        reader.Update()
        with open(stats) as s:
            return reader.GetOutput(), json.load(s)

    def test_every_property_has_its_option(self):
        for cls, props, args, changes in CASES:
            with self.subTest(filter=cls.__name__, properties=props):
                f = self.run_filter(cls, props)
                cli, stats = self.run_cli(cls, args)
                fp, ft = arrays(f.GetOutput())
                cp, ct = arrays(cli)
                self.assertEqual(fp.shape, cp.shape)
                self.assertTrue((fp == cp).all(), "points differ")
                self.assertTrue((ft == ct).all(), "triangles differ")
                self.assertEqual(f.GetOutputTriangles(), stats["output_triangles"])
                self.assertEqual(f.GetAchievedError(), stats["achieved_error"])
                self.assertEqual(f.GetPrunedComponents(), stats["pruned_components"])
                self.assertEqual(f.GetPrunedTriangles(), stats["pruned_triangles"])
                self.assertEqual(f.GetPrunedComponents(), 1 if "PruneSize" in props else 0)
                self.assertEqual(f.GetErrorDiagonal(), stats["diagonal"])
                self.assertEqual(f.GetGridDimension(), stats["grid"] or 0)
                skips = props.get("PreClusterGridDimension") == -1 and \
                    props.get("TargetNumberOfTriangles", 0) > 19125
                self.assertEqual(f.GetGridDimension() > 0, cls is vtkSIPMSSCluster or (
                    props.get("PreClusterGridDimension", 0) != 0 and not skips))
                if skips:  # (the target is above the sheet's triangles: nothing collapses)
                    self.assertEqual(f.GetAchievedError(), 0)
                else:
                    self.assertGreater(f.GetAchievedError(), 0)
                if "MaximumError" in props:
                    bound = props["MaximumError"] / (f.GetErrorDiagonal() if props.get("AbsoluteError") else 1)
                    self.assertLessEqual(f.GetAchievedError(), bound * (1 + 1e-6))
                self.assertEqual(bool(f.GetUsedOutOfCore()), stats["storage"]["used_out_of_core"])
                if props.get("OperationMode") == 2:
                    self.assertTrue(f.GetUsedOutOfCore())
                if props.get("OperationMode") == 1:
                    self.assertFalse(f.GetUsedOutOfCore())
                if not props:
                    self.defaults[cls] = (fp, ft)
                    continue
                default = self.defaults[cls]
                same = default[0].shape == fp.shape and (default[0] == fp).all() and \
                    default[1].shape == ft.shape and (default[1] == ft).all()
                self.assertEqual(not same, changes,
                                 "the result %s the default's" % ("equals" if same else "differs from"))

    def test_bad_values_get_the_same_words(self):
        """A NaN or an out-of-range value: the CLI exits 2 and the filter errors, in the same
        words after the parameter's name."""
        from vtkmodules.vtkCommonCore import VTK_STRING
        from vtkmodules.util.misc import calldata_type
        nan = float("nan")
        cases = [(vtkSIPMSSDecimate, "TargetReduction", nan, ["--reduction", "nan"], "--reduction"),
                 (vtkSIPMSSDecimate, "WeldDistance", float("inf"), ["--weld", "inf"], "--weld"),
                 (vtkSIPMSSDecimate, "MaximumError", nan, ["--max-error", "nan"], "--max-error"),
                 (vtkSIPMSSDecimate, "PruneSize", nan, ["--prune-size", "nan"], "--prune-size"),
                 (vtkSIPMSSDecimate, "Attributes", "keep:-1", ["--attributes", "keep:-1"],
                  "--attributes"),
                 (vtkSIPMSSCluster, "Attributes", "keep,,region", ["--attributes", "keep,,region"],
                  "--attributes"),
                 (vtkSIPMSSCluster, "BoundaryWeight", 2e9, ["--boundary-weight", "2e9"],
                  "--boundary-weight"),
                 (vtkSIPMSSDecimate, "MemoryBudgetMB", 0.01, ["--memory-mb", "0.01"], "--memory-mb")]
        for cls, prop, value, args, option in cases:
            with self.subTest(prop=prop):
                errors = []

                @calldata_type(VTK_STRING)
                def on_error(_obj, _event, text):
                    errors.append(text)
                f = cls()
                f.SetFileName(self.input)
                f.AddObserver("ErrorEvent", on_error)
                getattr(f, "Set" + prop)(value)
                f.Update()
                self.assertEqual(len(errors), 1, errors)
                words = errors[0].split(prop + " ", 1)[1].rstrip(".\n")
                algorithm = ["--algorithm", "cluster" if cls is vtkSIPMSSCluster else "decimate"]
                r = subprocess.run([CLI, "simplify", self.input,
                                    os.path.join(self.tmp.name, "bad.ply")] + algorithm + args,
                                   capture_output=True, text=True)
                self.assertEqual(r.returncode, 2, r.stderr)
                self.assertIn(option + ": " + words, r.stderr)


if __name__ == "__main__":
    result = unittest.main(exit=False).result
    sys.exit(0 if result.wasSuccessful() else 1)
