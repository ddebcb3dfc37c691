"""SIPMSS from VTK Python: both filters on a pipeline mesh and on a streamed file."""
import os
import sys
import tempfile
import unittest

from vtkmodules.vtkCommonCore import vtkVersion
from vtkmodules.vtkFiltersSources import vtkSphereSource
from vtkmodules.vtkIOPLY import vtkPLYWriter
from vtkmodules.vtkCommonTransforms import vtkTransform
from vtkmodules.vtkFiltersGeneral import vtkDistancePolyDataFilter, vtkTransformPolyDataFilter
import json
import random
import subprocess

from vtkmodules.vtkCommonCore import (VTK_DOUBLE, VTK_FLOAT, VTK_INT, VTK_LONG_LONG, VTK_STRING,
                                      VTK_UNSIGNED_CHAR, vtkDoubleArray, vtkFloatArray, vtkIdList,
                                      vtkIntArray,
                                      vtkLongLongArray, vtkPoints, vtkStringArray,
                                      vtkUnsignedCharArray)
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.util.misc import calldata_type

from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate, vtkSIPMSSFilterBase


class Messages:
    """Collects a filter's warning and error messages."""

    def __init__(self, f):
        self.warnings, self.errors = [], []

        @calldata_type(VTK_STRING)
        def on_warning(_obj, _event, text):
            self.warnings.append(text)

        @calldata_type(VTK_STRING)
        def on_error(_obj, _event, text):
            self.errors.append(text)

        f.AddObserver("WarningEvent", on_warning)
        f.AddObserver("ErrorEvent", on_error)


def poly_data(pts, polygons):
    """A vtkPolyData of these vtkPoints and polygons (point id sequences)."""
    cells = vtkCellArray()
    for ids in polygons:
        cells.InsertNextCell(len(ids), ids)
    pd = vtkPolyData()
    pd.SetPoints(pts)
    pd.SetPolys(cells)
    return pd


def unit_square_with(polygons):
    """The four corners of the unit square with these polygons (point id tuples)."""
    pts = vtkPoints()
    for p in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)):
        pts.InsertNextPoint(p)
    return poly_data(pts, polygons)


def attributed_sphere():
    """A sphere with point data of many kinds and roles, and cell data."""
    src = sphere(60)
    pd = vtkPolyData()
    pd.DeepCopy(src.GetOutput())
    n = pd.GetNumberOfPoints()
    rgb = vtkUnsignedCharArray()
    rgb.SetName("RGB")
    rgb.SetNumberOfComponents(3)
    tc = vtkFloatArray()
    tc.SetName("TextureCoordinates")
    tc.SetNumberOfComponents(2)
    label = vtkIntArray()
    label.SetName("Label")
    vel = vtkDoubleArray()
    vel.SetName("Velocity")
    vel.SetNumberOfComponents(3)
    vel.SetComponentName(0, "vx")
    big = vtkLongLongArray()
    big.SetName("Id64")
    names = vtkStringArray()
    names.SetName("Names")
    for i in range(n):
        x, y, z = pd.GetPoint(i)
        rgb.InsertNextTuple3(255 if x > 0 else 0, 128, 10)
        tc.InsertNextTuple2(x + 0.5, y + 0.5)
        label.InsertNextValue(0 if z < -0.2 else (3 if z < 0.2 else 7))
        vel.InsertNextTuple3(x, -y, 2 * z)
        big.InsertNextValue(1000 + i)
        names.InsertNextValue("p%d" % i)
    for a in (rgb, tc, label, vel, big, names):
        pd.GetPointData().AddArray(a)
    pd.GetPointData().SetActiveScalars("RGB")
    pd.GetPointData().SetActiveTCoords("TextureCoordinates")
    region = vtkIntArray()
    region.SetName("Region")
    for i in range(pd.GetNumberOfCells()):
        region.InsertNextValue(i % 3)
    pd.GetCellData().AddArray(region)
    return pd


def sphere(resolution=100):
    s = vtkSphereSource()
    s.SetThetaResolution(resolution)
    s.SetPhiResolution(resolution)
    s.Update()
    return s


class SIPMSSPythonTest(unittest.TestCase):
    def test_cluster_pipeline(self):
        src = sphere()
        f = vtkSIPMSSCluster()
        f.SetInputConnection(src.GetOutputPort())
        f.SetMaximumGridDimension(16)
        f.Update()
        out = f.GetOutput()
        n_in = src.GetOutput().GetNumberOfPolys()
        self.assertGreater(out.GetNumberOfPolys(), 50)
        self.assertLess(out.GetNumberOfPolys(), n_in)
        b = out.GetBounds()
        for lo, hi in zip(b[0::2], b[1::2]):
            self.assertGreaterEqual(lo, -0.5 - 1e-6)
            self.assertLessEqual(hi, 0.5 + 1e-6)
        self.assertTrue(f.GetUsedInCore())

    def test_decimate_pipeline(self):
        src = sphere()
        f = vtkSIPMSSDecimate()
        f.SetInputConnection(src.GetOutputPort())
        f.SetTargetReduction(0.8)
        f.Update()
        n_in = src.GetOutput().GetNumberOfPolys()
        n_out = f.GetOutput().GetNumberOfPolys()
        self.assertLessEqual(n_out, round(n_in * 0.2))
        self.assertGreater(n_out, round(n_in * 0.15))
        # one thread instead of all cores: the same mesh
        self.assertEqual(f.GetNumberOfThreads(), 0)
        g = vtkSIPMSSDecimate()
        g.SetInputConnection(src.GetOutputPort())
        g.SetTargetReduction(0.8)
        g.SetNumberOfThreads(1)
        g.Update()
        self.assertEqual(g.GetOutput().GetNumberOfPolys(), n_out)
        for i in range(0, f.GetOutput().GetNumberOfPoints(), 97):
            self.assertEqual(f.GetOutput().GetPoint(i), g.GetOutput().GetPoint(i))

    def test_ghost_cells_are_not_part_of_the_piece(self):
        # A piece with ghost cells (copies of another piece's cells, as D3 or
        # RedistributeDataSet make them, or hidden ones): both filters give what the piece
        # without them gives, and the ghost arrays are not carried.
        from vtkmodules.vtkCommonDataModel import vtkDataSetAttributes
        src = sphere(60)
        full = src.GetOutput()
        owned = vtkCellArray()
        ghosted = vtkPolyData()
        ghosted.DeepCopy(full)
        cell_ghosts = ghosted.AllocateCellGhostArray()
        point_ghosts = ghosted.AllocatePointGhostArray()
        ids = full.GetPolys()
        pts = [0, 0, 0]
        n_ghost = 0
        for c in range(full.GetNumberOfCells()):
            cell = full.GetCell(c)
            z = sum(full.GetPoint(cell.GetPointId(k))[2] for k in range(3)) / 3
            if z > 0.2:
                kind = (vtkDataSetAttributes.DUPLICATECELL if c % 2 else
                        vtkDataSetAttributes.HIDDENCELL)
                cell_ghosts.SetValue(c, kind)
                n_ghost += 1
                for k in range(3):
                    point_ghosts.SetValue(cell.GetPointId(k), vtkDataSetAttributes.DUPLICATEPOINT)
            else:
                owned.InsertNextCell(3, [cell.GetPointId(k) for k in range(3)])
        self.assertGreater(n_ghost, 100)
        reference = vtkPolyData()
        reference.SetPoints(full.GetPoints())
        reference.SetPolys(owned)
        reference.GetPointData().ShallowCopy(full.GetPointData())
        for make in (lambda: vtkSIPMSSCluster(), lambda: vtkSIPMSSDecimate()):
            outs = []
            for pd in (ghosted, reference):
                f = make()
                messages = Messages(f)
                f.SetInputData(pd)
                if isinstance(f, vtkSIPMSSDecimate):
                    f.SetTargetNumberOfTriangles(500)
                else:
                    f.SetMaximumGridDimension(20)
                f.Update()
                self.assertNotIn("vtkGhostType", " ".join(messages.warnings))
                outs.append(f.GetOutput())
            got, want = outs
            name = got.GetClassName()
            self.assertEqual(got.GetNumberOfPolys(), want.GetNumberOfPolys(), name)
            self.assertEqual(got.GetNumberOfPoints(), want.GetNumberOfPoints(), name)
            for i in range(got.GetNumberOfPoints()):
                self.assertEqual(got.GetPoint(i), want.GetPoint(i))
            self.assertIsNone(got.GetPointData().GetArray("vtkGhostType"))
            self.assertIsNone(got.GetCellData().GetArray("vtkGhostType"))
            self.assertEqual(got.GetPointData().GetNumberOfArrays(),
                             want.GetPointData().GetNumberOfArrays())

    def test_file_array_names_read_the_header_of_a_regular_file_only(self):
        # The choices of LockArray and SelectionArray for a FileName run: the PLY header's
        # vertex properties, then its face properties. A pipe is never opened for them (its
        # bytes belong to the run): no writer here, and the call returns at once, empty.
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "p.ply")
            with open(path, "w") as f:
                f.write("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                        "property float y\nproperty float z\nproperty uchar keep\n"
                        "element face 1\nproperty list uchar int vertex_indices\n"
                        "property uchar sel\nend_header\n0 0 0 1\n1 0 0 0\n0 1 0 0\n"
                        "3 0 1 2 1\n")
            f = vtkSIPMSSDecimate()
            names = lambda a: [a.GetValue(i) for i in range(a.GetNumberOfValues())]
            self.assertEqual(names(f.GetFilePointArrayNames()), [])
            f.SetFileName(path)
            self.assertEqual(names(f.GetFilePointArrayNames()), ["keep"])
            self.assertEqual(names(f.GetFileArrayNames()), ["keep", "sel"])
            fifo = os.path.join(tmp, "pipe.ply")
            os.mkfifo(fifo)
            with open(path, "rb") as src:
                content = src.read()

            def write():  # (blocks until a reader opens the pipe)
                with open(fifo, "wb") as w:
                    w.write(content)

            import threading
            writer = threading.Thread(target=write, daemon=True)
            writer.start()
            f.SetFileName(fifo)
            self.assertEqual(names(f.GetFilePointArrayNames()), [])
            self.assertEqual(names(f.GetFileArrayNames()), [])
            # every byte is still there for the run
            with open(fifo, "rb") as r:
                self.assertEqual(r.read(), content)
            writer.join(10)
            self.assertFalse(writer.is_alive())

    def test_cell_selection_keeps_the_cells_outside_it(self):
        """SelectionArray naming a cell array of a pipeline mesh: every triangle outside the
        selection (the cells where it is 0) is in the output with the same corners."""
        src = sphere()
        src.Update()
        pd = vtkPolyData()
        pd.DeepCopy(src.GetOutput())
        sel = vtkUnsignedCharArray()
        sel.SetName("picked")
        outside = set()
        for c in range(pd.GetNumberOfCells()):
            ids = vtkIdList()
            pd.GetCellPoints(c, ids)
            pts = [pd.GetPoint(ids.GetId(k)) for k in range(ids.GetNumberOfIds())]
            inside = sum(p[2] for p in pts) / len(pts) > -0.1
            sel.InsertNextValue(1 if inside else 0)
            if not inside:
                outside.add(tuple(sorted(pts)))
        pd.GetCellData().AddArray(sel)
        f = vtkSIPMSSDecimate()
        f.SetInputData(pd)
        f.SetTargetNumberOfTriangles(300)
        f.SetSelectionArray("picked")
        f.Update()
        out = f.GetOutput()
        self.assertLess(out.GetNumberOfPolys(), pd.GetNumberOfPolys())
        got = set()
        for c in range(out.GetNumberOfCells()):
            ids = vtkIdList()
            out.GetCellPoints(c, ids)
            got.add(tuple(sorted(out.GetPoint(ids.GetId(k)) for k in range(3))))
        self.assertTrue(outside)
        self.assertEqual(outside - got, set())
        # a name that is neither a point nor a cell array: an error naming both lists
        m = Messages(f)
        f.SetSelectionArray("absent")
        f.Update()
        self.assertEqual(len(m.errors), 1, m.errors)
        self.assertIn("cell arrays: picked", m.errors[0])

    def test_stream_file_out_of_core(self):
        data = os.environ.get("SIPMSS_SHARED_DATA_DIR", "")
        bunny = os.path.join(data, "bunny.ply")
        with tempfile.TemporaryDirectory() as tmp:
            if not os.path.exists(bunny):
                print("shared data absent: streaming a generated sphere instead of bunny.ply")
                bunny = os.path.join(tmp, "sphere.ply")
                src = sphere(200)  # keep the source alive while the writer uses its port
                w = vtkPLYWriter()
                w.SetInputConnection(src.GetOutputPort())
                w.SetFileName(bunny)
                w.Write()
            f = vtkSIPMSSCluster()
            f.SetFileName(bunny)
            f.SetMaximumGridDimension(40)
            f.SetMemoryBudgetMB(0.25)
            f.SetOperationMode(vtkSIPMSSFilterBase.OUT_OF_CORE)
            f.SetTemporaryDirectories(tmp)
            f.Update()
            self.assertGreater(f.GetOutput().GetNumberOfPolys(), 500)
            self.assertTrue(f.GetUsedOutOfCore())
            self.assertLessEqual(f.GetPeakStorageBytes(), 256 * 1024)
            # the private block directory is gone
            left = [n for n in os.listdir(tmp) if n.startswith("sipmss-")]
            self.assertEqual(left, [])

    def test_compare_agrees_with_vtk_distance(self):
        """`sipmss compare` against VTK's vtkDistancePolyDataFilter on a sphere and its 1.1x copy."""
        cli = os.environ.get("SIPMSS_CLI")
        if not cli:
            self.skipTest("SIPMSS_CLI is not set")
        ref = sphere(60)
        t = vtkTransform()
        t.Scale(1.1, 1.1, 1.1)
        scaled = vtkTransformPolyDataFilter()
        scaled.SetTransform(t)
        scaled.SetInputConnection(ref.GetOutputPort())
        scaled.Update()
        with tempfile.TemporaryDirectory() as tmp:
            paths = []
            for name, alg in (("ref.ply", ref), ("cand.ply", scaled)):
                w = vtkPLYWriter()
                w.SetFileName(os.path.join(tmp, name))
                w.SetInputConnection(alg.GetOutputPort())
                w.Write()
                paths.append(os.path.join(tmp, name))
            out = subprocess.run([cli, "compare", paths[0], paths[1], "--samples", "100000"],
                                 check=True, capture_output=True, text=True).stdout
            ours = json.loads(out)
        d = vtkDistancePolyDataFilter()
        d.SetInputConnection(0, ref.GetOutputPort())
        d.SetInputConnection(1, scaled.GetOutputPort())
        d.SignedDistanceOff()
        d.ComputeSecondDistanceOn()
        d.Update()
        a = d.GetOutput().GetPointData().GetArray("Distance")
        b = d.GetSecondDistanceOutput().GetPointData().GetArray("Distance")
        vals = [a.GetValue(i) for i in range(a.GetNumberOfTuples())] + \
               [b.GetValue(i) for i in range(b.GetNumberOfTuples())]
        vtk_max = max(vals)
        vtk_mean = sum(vals) / len(vals)
        # every distance is about 0.05 (sphere radius 0.5 scaled by 1.1), up to the facets' sagitta
        self.assertAlmostEqual(ours["hausdorff_absolute"], vtk_max, delta=0.03 * vtk_max)
        self.assertAlmostEqual(ours["mean_absolute"], vtk_mean, delta=0.03 * vtk_mean)
        self.assertAlmostEqual(ours["diagonal"], 3 ** 0.5, delta=1e-3)


    def test_arrays_keep_names_types_and_roles(self):
        pd = attributed_sphere()
        expect = {"Normals": (3, VTK_FLOAT), "RGB": (3, VTK_UNSIGNED_CHAR),
                  "TextureCoordinates": (2, VTK_FLOAT), "Label": (1, VTK_INT),
                  "Velocity": (3, VTK_DOUBLE), "Id64": (1, VTK_LONG_LONG)}
        cluster = vtkSIPMSSCluster()
        cluster.SetMaximumGridDimension(20)
        decimate = vtkSIPMSSDecimate()
        decimate.SetTargetNumberOfTriangles(500)
        decimate.SetNumberOfLevelsOfDetail(2)
        two_stage = vtkSIPMSSDecimate()
        two_stage.SetTargetNumberOfTriangles(500)
        two_stage.SetPreClusterGridDimension(30)
        for f in (cluster, decimate, two_stage):
            msgs = Messages(f)
            f.SetInputData(pd)
            f.Update()
            outputs = [f.GetOutput()]
            if f is decimate:
                lods = f.GetOutputDataObject(1)
                outputs += [lods.GetBlock(i) for i in range(lods.GetNumberOfBlocks())]
            for out in outputs:
                self.assertGreater(out.GetNumberOfPolys(), 0)
                opd = out.GetPointData()
                got = {opd.GetArrayName(i): (opd.GetArray(i).GetNumberOfComponents(),
                                            opd.GetArray(i).GetDataType())
                       for i in range(opd.GetNumberOfArrays())}
                self.assertEqual(got, expect, f.GetClassName())
                self.assertEqual(opd.GetScalars().GetName(), "RGB")
                self.assertEqual(opd.GetTCoords().GetName(), "TextureCoordinates")
                self.assertEqual(opd.GetNormals().GetName(), "Normals")
                self.assertEqual(opd.GetArray("Velocity").GetComponentName(0), "vx")
                # integers take values the input has (nearest, never a fraction)
                labels = {opd.GetArray("Label").GetValue(i) for i in range(out.GetNumberOfPoints())}
                self.assertTrue(labels <= {0, 1, 2, 3, 4, 5, 6, 7}, labels)
                red = {opd.GetArray("RGB").GetComponent(i, 0) for i in range(out.GetNumberOfPoints())}
                self.assertTrue(red <= set(float(v) for v in range(256)))
            # what is not carried is named once in a warning
            text = " ".join(msgs.warnings)
            self.assertIn("Region", text)
            self.assertIn("Names", text)
            self.assertEqual(msgs.errors, [])

    def assert_both_filters_refuse(self, pd, says, empty="GetNumberOfPoints"):
        """Both filters give an empty output (`empty` counts 0) and one error that says `says`."""
        for f in (vtkSIPMSSCluster(), vtkSIPMSSDecimate()):
            msgs = Messages(f)
            f.SetInputData(pd)
            f.Update()
            self.assertEqual(getattr(f.GetOutput(), empty)(), 0)
            self.assertEqual(len(msgs.errors), 1, msgs.errors)
            self.assertIn(says, msgs.errors[0])

    def test_non_finite_points_are_an_error(self):
        for bad in (float("nan"), float("inf")):
            pd = vtkPolyData()
            pd.DeepCopy(sphere(20).GetOutput())
            pd.GetPoints().SetPoint(7, 0.1, bad, 0.2)
            self.assert_both_filters_refuse(pd, "point 7 has a non-finite coordinate")

    def test_points_beyond_single_precision_are_an_error(self):
        # found by the VTK bridge fuzzer: a double beyond FLT_MAX came out as an infinite point
        pd = vtkPolyData()
        pd.DeepCopy(sphere(20).GetOutput())
        points = vtkPoints()
        points.SetDataTypeToDouble()
        points.DeepCopy(pd.GetPoints())
        points.SetPoint(3, 1e39, 0.0, 0.0)
        pd.SetPoints(points)
        self.assert_both_filters_refuse(pd, "point 3 has a coordinate beyond single precision")

    def test_point_ids_are_checked_in_64_bits(self):
        pd = unit_square_with([(0, 1, 3), (0, 1, 2 ** 32 + 2)])  # must not wrap to (0, 1, 2)
        self.assert_both_filters_refuse(pd, "references point id 4294967298, but the input has 4 points",
                                        empty="GetNumberOfPolys")

    def test_point_arrays_of_the_wrong_length_are_dropped(self):
        # found by the VTK bridge fuzzer: an array shorter than the points was read past its end
        pd = vtkPolyData()
        pd.DeepCopy(attributed_sphere())
        short = vtkFloatArray()
        short.SetName("Short")
        short.SetNumberOfTuples(pd.GetNumberOfPoints() - 5)
        short.Fill(1.0)
        pd.GetPointData().AddArray(short)
        for f in (vtkSIPMSSCluster(), vtkSIPMSSDecimate()):
            msgs = Messages(f)
            f.SetInputData(pd)
            f.Update()
            self.assertEqual(msgs.errors, [])
            self.assertGreater(f.GetOutput().GetNumberOfPolys(), 0)
            self.assertIsNone(f.GetOutput().GetPointData().GetArray("Short"))
            self.assertIsNotNone(f.GetOutput().GetPointData().GetArray("Label"))
            self.assertTrue(any("Short (%d tuples)" % (pd.GetNumberOfPoints() - 5) in w
                                for w in msgs.warnings), msgs.warnings)
            self.assertIsNotNone(pd.GetPointData().GetArray("Short"))  # the input keeps it

    def test_dropped_faces_are_reported(self):
        # two good triangles, one with a repeated vertex, one with two vertices
        pd = unit_square_with([(0, 1, 3), (0, 3, 2), (1, 1, 2), (1, 2)])
        for f in (vtkSIPMSSCluster(), vtkSIPMSSDecimate()):
            msgs = Messages(f)
            f.SetInputData(pd)
            f.Update()
            self.assertEqual(msgs.errors, [])
            self.assertTrue(any("Dropped 2 degenerate faces of the input" in w for w in msgs.warnings),
                            msgs.warnings)

    def test_meaningless_parameters_are_errors(self):
        """The CLI's rules: NaN, infinities and budgets that round to nothing are errors."""
        src = sphere(20)  # alive while the filters use its port
        nan, inf = float("nan"), float("inf")
        cases = [(vtkSIPMSSDecimate, "SetMemoryBudgetMB", nan, "MemoryBudgetMB must be 0 (automatic), -1 (unbounded) or"),
                 (vtkSIPMSSDecimate, "SetMemoryBudgetMB", inf, "MemoryBudgetMB must be 0 (automatic), -1 (unbounded) or"),
                 (vtkSIPMSSCluster, "SetMemoryBudgetMB", 1e-7, "MemoryBudgetMB must be 0 (automatic), -1 (unbounded) or"),
                 (vtkSIPMSSDecimate, "SetTargetReduction", nan, "TargetReduction must be a finite number"),
                 (vtkSIPMSSDecimate, "SetBoundaryWeight", nan, "BoundaryWeight must be a finite number"),
                 (vtkSIPMSSDecimate, "SetWeldDistance", inf, "WeldDistance must be a finite number"),
                 (vtkSIPMSSDecimate, "SetMaximumError", nan, "MaximumError must be a number"),
                 (vtkSIPMSSCluster, "SetBoundaryWeight", nan, "BoundaryWeight must be a finite number")]
        for cls, setter, value, says in cases:
            f = cls()
            msgs = Messages(f)
            f.SetInputConnection(src.GetOutputPort())
            getattr(f, setter)(value)
            f.Update()
            self.assertEqual(f.GetOutput().GetNumberOfPolys(), 0, setter)
            self.assertEqual(len(msgs.errors), 1, (setter, msgs.errors))
            self.assertIn(says, msgs.errors[0])
        f = vtkSIPMSSCluster()
        msgs = Messages(f)
        f.SetInputConnection(src.GetOutputPort())
        f.SetMemoryBudgetMB(-0.5)
        f.Update()
        self.assertEqual(len(msgs.errors), 1, msgs.errors)
        self.assertIn("MemoryBudgetMB must be 0 (automatic), -1 (unbounded) or", msgs.errors[0])
        # still fine: an infinite MaximumError (no bound) and the smallest budget
        f = vtkSIPMSSDecimate()
        f.SetInputConnection(src.GetOutputPort())
        f.SetMaximumError(inf)
        f.SetMemoryBudgetMB(0.0625)
        f.Update()
        self.assertGreater(f.GetOutput().GetNumberOfPolys(), 0)

    def test_memory_budget_is_automatic_by_default(self):
        """MemoryBudgetMB 0 (the default) is a share of what the process may use, -1 unbounded,
        a number that many MiB; the run reports the budget it had."""
        src = sphere(40)
        outputs = []
        for cls in (vtkSIPMSSCluster, vtkSIPMSSDecimate):
            self.assertEqual(cls().GetMemoryBudgetMB(), 0.0)
            for budget, expect in ((0, None), (-1, 0), (8, 8 << 20)):
                f = cls()
                msgs = Messages(f)
                f.SetInputConnection(src.GetOutputPort())
                f.SetMemoryBudgetMB(budget)
                f.Update()
                self.assertEqual(msgs.errors, [])
                if expect is None:
                    # half of MemAvailable (or of a lower limit), never unbounded on Linux
                    with open("/proc/meminfo") as m:
                        avail = next(int(line.split()[1]) * 1024 for line in m
                                     if line.startswith("MemAvailable:"))
                    self.assertGreater(f.GetMemoryBudgetBytes(), 0)
                    self.assertLessEqual(f.GetMemoryBudgetBytes(), avail // 2 + (64 << 20))
                else:
                    self.assertEqual(f.GetMemoryBudgetBytes(), expect)
                self.assertTrue(f.GetUsedInCore())
                outputs.append(f.GetOutput().GetNumberOfPolys())
        # the budget does not change the result
        self.assertEqual(len(set(outputs[:3])), 1, outputs)
        self.assertEqual(len(set(outputs[3:])), 1, outputs)

    def test_a_shuffled_input_is_reordered(self):
        """A vtkPolyData whose points and triangles are in random order is reordered before the
        run (the statistics say so); the same surface in order is not; both give an output of
        the same size, and the shuffled one keeps its point array."""
        src = sphere(300)  # 89,402 points, 178,800 triangles, in theta/phi order
        pd = src.GetOutput()
        n = pd.GetNumberOfPoints()
        perm = list(range(n))
        random.Random(3).shuffle(perm)
        pts = vtkPoints()
        pts.SetNumberOfPoints(n)
        ids = vtkIntArray()
        ids.SetName("OriginalId")
        ids.SetNumberOfTuples(n)
        for old in range(n):
            pts.SetPoint(perm[old], pd.GetPoint(old))
            ids.SetValue(perm[old], old)
        tris = []
        cells = pd.GetPolys()
        cells.InitTraversal()
        idl = vtkIdList()
        while cells.GetNextCell(idl):
            tris.append([perm[idl.GetId(k)] for k in range(idl.GetNumberOfIds())])
        random.Random(4).shuffle(tris)
        shuffled = poly_data(pts, tris)
        shuffled.GetPointData().AddArray(ids)
        sizes = []
        for data, expect in ((pd, False), (shuffled, True)):
            f = vtkSIPMSSDecimate()
            f.SetInputData(data)
            f.SetTargetNumberOfTriangles(5000)
            f.Update()
            self.assertEqual(f.GetReordered(), expect)
            if expect:
                self.assertGreater(f.GetLayoutFarFraction(), 0.5)
                self.assertIsNotNone(f.GetOutput().GetPointData().GetArray("OriginalId"))
            else:
                self.assertLess(f.GetLayoutFarFraction(), 0.05)
            sizes.append(f.GetOutput().GetNumberOfPolys())
        self.assertLess(abs(sizes[0] - sizes[1]), 0.01 * sizes[0] + 2, sizes)


if __name__ == "__main__":
    print("VTK", vtkVersion.GetVTKVersion(), "python", sys.version.split()[0])
    unittest.main()
