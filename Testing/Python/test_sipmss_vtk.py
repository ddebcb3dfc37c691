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
import subprocess

from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate, vtkSIPMSSFilterBase


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


if __name__ == "__main__":
    print("VTK", vtkVersion.GetVTKVersion(), "python", sys.version.split()[0])
    unittest.main()
