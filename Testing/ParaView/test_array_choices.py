"""pvpython: Lock Array and Selection Array are drop-downs of the arrays a run can use.

- SIPMSS Decimate (a pipeline input): the input's one-component point arrays for Lock Array, its
  one-component point and cell arrays for Selection Array, after an empty entry ("none", the
  default).
- SIPMSS Decimate File and its File > Open reader: the file's vertex properties for Lock Array,
  its vertex then face properties for Selection Array (read from the PLY header when the file is
  chosen), after the same empty entry.
- A name taken from the list locks its vertices: they are in the output, unmoved; without it
  they are not all there (the check can fail).
"""
import os
import tempfile

from paraview import servermanager
from paraview.simple import *  # noqa: F401,F403

LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=False, ns=globals())
errors = []


def choices(proxy, name):
    domain = proxy.GetProperty(name).SMProperty.GetDomain("array_list")
    return [domain.GetString(i) for i in range(domain.GetNumberOfStrings())]


def expect(what, got, want):
    if got != want:
        errors.append("%s: %r, expected %r" % (what, got, want))


def kept_points(dataset, flags):
    return {dataset.GetPoint(i) for i in range(dataset.GetNumberOfPoints()) if flags(i)}


def output_points(proxy):
    out = servermanager.Fetch(proxy)
    return {out.GetPoint(i) for i in range(out.GetNumberOfPoints())}


sphere = Sphere(ThetaResolution=60, PhiResolution=60)
mask = Calculator(Input=sphere, ResultArrayName="mask", Function="coordsX > 0.49")
band = Calculator(Input=mask, ResultArrayName="band", Function="abs(coordsZ) < 0.1")
vec = Calculator(Input=band, ResultArrayName="vec", Function="coordsX*iHat + coordsY*jHat")
cells = PointDatatoCellData(Input=vec, PassPointData=1, ProcessAllArrays=0,
                            PointDataArraytoprocess=["band"])
cells.UpdatePipeline()

# --- the filter: arrays of its input
decimate = SIPMSSDecimate(Input=cells, TargetNumberOfTriangles=300)
point_arrays = sorted(a for a in ("mask", "band"))  # one component (not Normals, not vec)
lock = choices(decimate, "LockArray")
expect("filter LockArray choices", lock[:1], [""])
expect("filter LockArray arrays", sorted(lock[1:]), point_arrays)
selection = choices(decimate, "SelectionArray")
expect("filter SelectionArray choices", selection[:1], [""])
# "band" is both a point and a cell array: the list has it twice (one per association)
expect("filter SelectionArray arrays", sorted(selection[1:]), sorted(point_arrays + ["band"]))
expect("filter LockArray default", decimate.LockArray, "")
expect("filter SelectionArray default", decimate.SelectionArray, "")

data = servermanager.Fetch(cells)
flags = data.GetPointData().GetArray("mask")
locked = kept_points(data, lambda i: flags.GetValue(i) != 0)
if not 5 < len(locked) < data.GetNumberOfPoints() // 10:
    errors.append("the mask locks %d of %d points" % (len(locked), data.GetNumberOfPoints()))
decimate.UpdatePipeline()
if locked <= output_points(decimate):
    errors.append("without a Lock Array every masked vertex stayed: the check cannot fail")
decimate.LockArray = lock[lock.index("mask")]
decimate.UpdatePipeline()
if not locked <= output_points(decimate):
    errors.append("filter: %d of the %d vertices locked by 'mask' moved or went" %
                  (len(locked - output_points(decimate)), len(locked)))

# --- the file sources: properties of the file's header
with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "masked.ply")
    tri = servermanager.Fetch(Triangulate(Input=sphere))
    n = tri.GetNumberOfPoints()
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
                "property float z\nproperty uchar keep\nproperty float weight\n"
                "element face %d\nproperty list uchar int vertex_indices\nproperty uchar sel\n"
                "end_header\n" % (n, tri.GetNumberOfCells()))
        file_locked = set()
        for i in range(n):
            p = tri.GetPoint(i)
            keep = 1 if p[0] > 0.49 else 0
            f.write("%r %r %r %d 0.5\n" % (p[0], p[1], p[2], keep))
        ids = tri.GetPolys().GetConnectivityArray()
        for c in range(tri.GetNumberOfCells()):
            f.write("3 %d %d %d %d\n" % (ids.GetValue(3 * c), ids.GetValue(3 * c + 1),
                                         ids.GetValue(3 * c + 2), c % 2))
    for make in (SIPMSSDecimateFile, SIPMSSDecimateFileReader):
        src = make(FileName=path, TargetNumberOfTriangles=300)
        src.UpdatePipelineInformation()
        label = src.GetXMLName()
        expect(label + " LockArray choices", choices(src, "LockArray"), ["", "keep", "weight"])
        expect(label + " SelectionArray choices", choices(src, "SelectionArray"),
               ["", "keep", "weight", "sel"])
        info = src.SMProxy.GetProperty("FilePointArrayNames")
        expect(label + " FilePointArrayNames",
               [info.GetElement(i) for i in range(info.GetNumberOfElements())], ["keep", "weight"])
        src.LockArray = "keep"
        src.UpdatePipeline()
        out = servermanager.Fetch(src)
        keep = out.GetPointData().GetArray("keep")
        kept = {out.GetPoint(i) for i in range(out.GetNumberOfPoints()) if keep.GetValue(i)}
        want = {p for p in kept_points(tri, lambda i: tri.GetPoint(i)[0] > 0.49)}
        # (the PLY holds the positions as floats: compare at float precision)
        import struct
        as_float = lambda s: {struct.unpack("3f", struct.pack("3f", *p)) for p in s}
        if not want or as_float(want) != as_float(kept):
            errors.append("%s: the %d vertices 'keep' locks are not the output's %d kept ones" %
                          (label, len(want), len(kept)))
        Delete(src)
    # a file without named properties, and no file: only the empty entry
    empty = SIPMSSDecimateFile(FileName=os.path.join(tmp, "missing.ply"))
    empty.UpdatePipelineInformation()
    expect("missing file LockArray choices", choices(empty, "LockArray"), [""])

if errors:
    raise SystemExit("FAILED:\n  " + "\n  ".join(errors))
print("Lock Array and Selection Array drop-downs: filter %s / %s, file sources checked" %
      (lock, selection))
