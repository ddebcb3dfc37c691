"""SIPMSS from VTK Python: both filters on a pipeline mesh and on a streamed file."""
import os
import sys
import tempfile
import unittest

from vtkmodules.vtkCommonCore import vtkVersion
from vtkmodules.vtkFiltersSources import vtkSphereSource
from vtkmodules.vtkIOPLY import vtkPLYWriter

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

    def test_stream_file_out_of_core(self):
        data = os.environ.get("SIPMSS_SHARED_DATA_DIR", "")
        bunny = os.path.join(data, "bunny.ply")
        with tempfile.TemporaryDirectory() as tmp:
            if not os.path.exists(bunny):
                print("shared data absent: streaming a generated sphere instead of bunny.ply")
                bunny = os.path.join(tmp, "sphere.ply")
                w = vtkPLYWriter()
                w.SetInputConnection(sphere(200).GetOutputPort())
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


if __name__ == "__main__":
    print("VTK", vtkVersion.GetVTKVersion(), "python", sys.version.split()[0])
    unittest.main()
