"""vtkSIPMSSDecimate's ProgressEvent on a generated mesh of about a million triangles, in core and
at MemoryBudgetMB=8: the progress never decreases, starts near 0 and ends at 1; an abort asked
for from the observer returns quickly. Also the cluster and two-stage filters."""
import math
import time
import unittest

from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray

from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate

try:
    import numpy as np
except ImportError:  # pragma: no cover - numpy comes with VTK's Python packages
    np = None


def bumpy_grid(n):
    """A bumpy height field on an n x n grid: 2 n^2 triangles."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    x, y = i.ravel() / n, j.ravel() / n
    z = 0.05 * np.sin(23.0 * x) * np.cos(17.0 * y) + 0.01 * np.sin(157.0 * x + 91.0 * y)
    xyz = np.ascontiguousarray(np.stack([x, y, z], axis=1), dtype=np.float32)
    a = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
    b, c = a + 1, a + n + 1
    d = c + 1
    tris = np.stack([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], 1).reshape(-1, 3)
    points = vtkPoints()
    points.SetData(numpy_to_vtk(xyz, deep=True))
    offsets = np.arange(0, 3 * len(tris) + 1, 3, dtype=np.int64)
    cells = vtkCellArray()
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(tris.astype(np.int64).ravel(), deep=True))
    pd = vtkPolyData()
    pd.SetPoints(points)
    pd.SetPolys(cells)
    return pd


class ProgressRecorder:
    """Records (time, progress) of every ProgressEvent; can abort at a given progress."""

    def __init__(self, f, abort_at=None):
        self.events = []
        self.abort_at = abort_at
        self.abort_time = None
        self.start = time.monotonic()

        def on_progress(obj, _event):
            self.events.append((time.monotonic() - self.start, obj.GetProgress()))
            if (self.abort_at is not None and self.abort_time is None
                    and obj.GetProgress() >= self.abort_at):
                self.abort_time = time.monotonic()
                obj.SetAbortExecute(1)

        f.AddObserver("ProgressEvent", on_progress)


@unittest.skipIf(np is None, "numpy is not available")
class ProgressTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.mesh = bumpy_grid(710)  # about 1.01M triangles

    def make(self, kind, budget_mb):
        if kind == "cluster":
            f = vtkSIPMSSCluster()
            f.SetMaximumGridDimension(100)
        else:
            f = vtkSIPMSSDecimate()
            f.SetTargetNumberOfTriangles(10000)
            if kind == "two-stage":
                f.SetPreClusterGridDimension(100)
        f.SetInputData(self.mesh)
        f.SetMemoryBudgetMB(budget_mb)
        return f

    def check_monotonic(self, kind, budget_mb):
        f = self.make(kind, budget_mb)
        rec = ProgressRecorder(f)
        f.Update()
        self.assertGreater(f.GetOutput().GetNumberOfPolys(), 0)
        values = [p for _, p in rec.events]
        what = "%s %s" % (kind, "at %d MB" % budget_mb if budget_mb else "in core")
        self.assertGreaterEqual(len(values), 3, what)
        drops = [(values[k - 1], values[k]) for k in range(1, len(values))
                 if values[k] < values[k - 1]]
        self.assertEqual(drops, [], "%s: the progress goes back" % what)
        self.assertLessEqual(values[0], 0.01, what)
        self.assertEqual(values[-1], 1.0, what)
        # Events come at least every 0.2 s (the bridge reports every 0.05 s), loosely: the test
        # machine may be busy.
        times = [0.0] + [t for t, _ in rec.events]
        gap = max(b - a for a, b in zip(times, times[1:]))
        self.assertLess(gap, 1.0, "%s: %.2f s without a progress event" % (what, gap))
        print("%s: %d events over %.2f s, longest gap %.3f s" % (what, len(values), times[-1], gap))
        return times[-1]

    def test_decimate_in_core(self):
        self.check_monotonic("decimate", 0)

    def test_decimate_at_8mb(self):
        self.check_monotonic("decimate", 8)

    def test_cluster(self):
        self.check_monotonic("cluster", 0)
        self.check_monotonic("cluster", 8)

    def test_two_stage(self):
        self.check_monotonic("two-stage", 0)

    def test_abort(self):
        """Aborting from the observer returns an empty output within 0.2 s (best of three, the
        machine may be busy), in core and at 8 MB."""
        for budget in (0, 8):
            for at in (0.1, 0.5, 0.8):
                best = math.inf
                for _ in range(3):
                    f = self.make("decimate", budget)
                    rec = ProgressRecorder(f, abort_at=at)
                    f.Update()
                    end = time.monotonic()
                    self.assertIsNotNone(rec.abort_time)
                    self.assertEqual(f.GetOutput().GetNumberOfPolys(), 0)
                    best = min(best, end - rec.abort_time)
                    if best <= 0.2:
                        break
                self.assertLessEqual(best, 0.2, "abort at %s, %s MB: %.3f s" % (at, budget, best))


if __name__ == "__main__":
    unittest.main()
