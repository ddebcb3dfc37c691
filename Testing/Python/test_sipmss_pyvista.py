"""SIPMSS with pyvista (optional: pyvista is not packaged for Debian bookworm)."""
import sys
import unittest

try:
    import pyvista as pv
except ImportError:
    print("SKIP: pyvista is not installed (see README: 'pyvista')")
    sys.exit(125)

from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate


class SIPMSSPyvistaTest(unittest.TestCase):
    def test_cluster_and_decimate(self):
        mesh = pv.Sphere(theta_resolution=120, phi_resolution=120)
        c = vtkSIPMSSCluster()
        c.SetInputData(mesh)
        c.SetMaximumGridDimension(20)
        c.Update()
        clustered = pv.wrap(c.GetOutput())
        self.assertGreater(clustered.n_cells, 100)
        self.assertLess(clustered.n_cells, mesh.n_cells)
        d = vtkSIPMSSDecimate()
        d.SetInputData(mesh)
        d.SetTargetNumberOfTriangles(2000)
        d.Update()
        self.assertLessEqual(pv.wrap(d.GetOutput()).n_cells, 2000)


if __name__ == "__main__":
    unittest.main()
