"""mpirun -np 2 pvbatch: the SIPMSS filters run on a distributed mesh (one piece per rank)."""
import os

from paraview import servermanager
from paraview.simple import *  # noqa: F401,F403

LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=True, ns=globals())

pm = servermanager.vtkProcessModule.GetProcessModule()
ranks = pm.GetNumberOfLocalPartitions()
assert ranks == 2, "expected 2 MPI ranks, got %d" % ranks

sphere = Sphere(ThetaResolution=160, PhiResolution=160)
redistributed = RedistributeDataSet(Input=sphere) if "RedistributeDataSet" in globals() else sphere
surface = ExtractSurface(Input=redistributed)
cluster = SIPMSSCluster(Input=surface)
cluster.MaximumGridDimension = 20
cluster.UpdatePipeline()
info = cluster.GetDataInformation()
n = info.GetNumberOfCells()
assert n > 100, n

decimate = SIPMSSDecimate(Input=surface)
decimate.TargetReduction = 0.75
decimate.NumberOfThreads = 1  # one thread per rank: the ranks share the cores
decimate.UpdatePipeline()
n_in = surface.GetDataInformation().GetNumberOfCells()
n_dec = decimate.GetDataInformation().GetNumberOfCells()
assert 0 < n_dec <= n_in * 0.25 + 2 * ranks, (n_dec, n_in)
print("pvbatch with %d ranks: cluster %d cells, decimate %d of %d" % (ranks, n, n_dec, n_in))
