"""pvpython: the SIPMSS plugin loads (LoadPlugin or PV_PLUGIN_PATH) and both filters work."""
import os
import sys
import tempfile

from paraview import servermanager
from paraview.simple import *  # noqa: F401,F403

how = sys.argv[1] if len(sys.argv) > 1 else "loadplugin"
if how == "loadplugin":
    LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=False, ns=globals())
else:
    # PV_PLUGIN_PATH: the plugin is found there and loaded at start-up
    import paraview.simple as simple
    assert hasattr(simple, "SIPMSSCluster"), "SIPMSS was not loaded from PV_PLUGIN_PATH"

sphere = Sphere(ThetaResolution=120, PhiResolution=120)
sphere.UpdatePipeline()
n_in = sphere.GetDataInformation().GetNumberOfCells()

cluster = SIPMSSCluster(Input=sphere)
cluster.MaximumGridDimension = 16
cluster.UpdatePipeline()
n_cluster = cluster.GetDataInformation().GetNumberOfCells()
assert 50 < n_cluster < n_in, (n_cluster, n_in)

decimate = SIPMSSDecimate(Input=sphere)
decimate.TargetNumberOfTriangles = 1000
decimate.NumberOfLevelsOfDetail = 2
decimate.UpdatePipeline()
n_dec = decimate.GetDataInformation().GetNumberOfCells()
assert 800 <= n_dec <= 1000, n_dec
assert decimate.NumberOfThreads == 0, decimate.NumberOfThreads  # all cores
decimate.NumberOfThreads = 1
decimate.UpdatePipeline()
assert decimate.GetDataInformation().GetNumberOfCells() == n_dec

# attribute-aware error: a point array of the input and its normals by their VTK names
calc = Calculator(Input=sphere, ResultArrayName="band", Function="10*coordsX*coordsX")
plain = SIPMSSDecimate(Input=calc, TargetNumberOfTriangles=1000)
aware = SIPMSSDecimate(Input=calc, TargetNumberOfTriangles=1000, Attributes="band:1,Normals:0.5")
for f in (plain, aware):
    f.UpdatePipeline()
out_plain = servermanager.Fetch(plain)
out_aware = servermanager.Fetch(aware)
assert out_aware.GetPointData().GetArray("band") is not None
assert out_aware.GetPointData().GetNormals() is not None
assert out_aware.GetNumberOfCells() == out_plain.GetNumberOfCells() == 1000
differs = any(out_plain.GetPoint(i) != out_aware.GetPoint(i)
              for i in range(min(out_plain.GetNumberOfPoints(), out_aware.GetNumberOfPoints())))
assert differs, "the attributes changed nothing"

# stream a file without loading it first (the "SIPMSS Cluster File" source)
with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "sphere.ply")
    SaveData(path, proxy=Triangulate(Input=sphere))
    src = SIPMSSClusterFile(FileName=path)
    src.MaximumGridDimension = 16
    src.MemoryBudgetMB = 0.125
    src.OperationMode = "Out of core"
    src.UpdatePipeline()
    n_file = src.GetDataInformation().GetNumberOfCells()
    assert n_file == n_cluster, (n_file, n_cluster)

print("pvpython SIPMSS plugin test passed (%s): %d -> cluster %d, decimate %d" %
      (how, n_in, n_cluster, n_dec))
