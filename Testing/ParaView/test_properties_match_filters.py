"""pvpython: the ParaView proxies say what the VTK filters do.

For every SIPMSS proxy (both filters, both file sources, both File > Open readers), as ParaView
loaded them from the plugin's XML:
- every property with a default has the filter's default (the value Get<Name>() returns on a new
  filter object);
- every range domain has the filter's clamp: a min or max the XML gives is the setter's
  Get<Name>MinValue()/MaxValue(), and a bound the XML leaves open is the type's limit;
- the proxies of one filter class have the same parameters with the same defaults and domains,
  and every proxy has the storage properties, their group and the run's statistics;
- after a run, the information properties carry the filter's statistics.
"""
import os
import sys

from paraview import servermanager
from paraview.simple import LoadPlugin

LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=False, ns=globals())
import sipmss  # noqa: E402 (the VTK classes, for the filters' own defaults and clamps)

VTK_INT_MAX = 2**31 - 1
VTK_ID_MAX = 2**63 - 1
VTK_DOUBLE_MAX = 1e299  # vtkType.h

PROXIES = [("filters", "SIPMSSCluster"), ("filters", "SIPMSSDecimate"),
           ("sources", "SIPMSSClusterFile"), ("sources", "SIPMSSDecimateFile"),
           ("sources", "SIPMSSClusterFileReader"), ("sources", "SIPMSSDecimateFileReader")]
STORAGE = ["MemoryBudgetMB", "TemporaryDirectories", "OperationMode", "NumberOfThreads"]
STATISTICS = ["UsedOutOfCore", "MemoryBudgetBytes", "PeakStorageBytes", "PeakTemporaryFileBytes",
              "InputTriangles", "OutputTriangles", "AchievedReduction", "ElapsedSeconds",
              "LayoutFarFraction", "Reordered", "AchievedError", "ErrorDiagonal",
              "PrunedComponents", "PrunedTriangles", "GridDimension"]

pxm = servermanager.ProxyManager()
errors = []


def check(condition, message):
    if not condition:
        errors.append(message)


def domain(prop, class_names):
    it = prop.NewDomainIterator()
    it.Begin()
    while not it.IsAtEnd():
        d = it.GetDomain()
        if d.GetClassName() in class_names:
            return d
        it.Next()
    return None


def describe(group, name):
    """{property: (default, (min or None, max or None))} of a proxy's settable properties."""
    proxy = pxm.SMProxyManager.NewProxy(group, name)
    check(proxy is not None, "no proxy %s/%s" % (group, name))
    out = {}
    it = proxy.NewPropertyIterator()
    it.Begin()
    while not it.IsAtEnd():
        key, prop = it.GetKey(), it.GetProperty()
        it.Next()
        if prop.GetInformationOnly() or prop.GetClassName() not in (
                "vtkSMIntVectorProperty", "vtkSMDoubleVectorProperty", "vtkSMStringVectorProperty"):
            continue
        n = prop.GetNumberOfElements()
        default = tuple(prop.GetElement(i) for i in range(n))  # a new proxy holds its defaults
        rng = (None, None)
        d = domain(prop, ("vtkSMIntRangeDomain", "vtkSMDoubleRangeDomain"))
        if d is not None:
            rng = (d.GetMinimum(0) if d.GetMinimumExists(0) else None,
                   d.GetMaximum(0) if d.GetMaximumExists(0) else None)
        out[key] = (default, rng)
    return proxy, out


by_class = {}
for group, name in PROXIES:
    proxy, props = describe(group, name)
    cls = proxy.GetVTKClassName()
    vtk_object = getattr(sipmss, cls)()
    for key in STORAGE:
        check(key in props, "%s has no %s" % (name, key))
    for key in STATISTICS:
        p = proxy.GetProperty(key)
        check(p is not None and p.GetInformationOnly(),
              "%s has no information property %s" % (name, key))
    groups = [proxy.GetPropertyGroup(i).GetXMLLabel()
              for i in range(proxy.GetNumberOfPropertyGroups())]
    check("Memory and storage" in groups, "%s: no 'Memory and storage' group (%s)" % (name, groups))
    for key, (default, (lo, hi)) in props.items():
        if key == "FileName":
            continue
        getter = getattr(vtk_object, "Get" + key)
        actual = getter()
        actual = tuple(actual) if isinstance(actual, tuple) else (actual,)
        if isinstance(actual[0], str) or actual[0] is None:
            actual = tuple(a or "" for a in actual)
            check(default == actual, "%s.%s: XML default %r, filter %r" % (name, key, default, actual))
        else:
            check(len(default) == len(actual) and
                  all(float(a) == float(b) for a, b in zip(default, actual)),
                  "%s.%s: XML default %r, filter %r" % (name, key, default, actual))
        clamp_min = getattr(vtk_object, "Get%sMinValue" % key, None)
        clamp_max = getattr(vtk_object, "Get%sMaxValue" % key, None)
        if lo is None and hi is None:
            check(clamp_min is None or key in ("OperationMode",),
                  "%s.%s: the filter clamps to [%s, %s], the XML has no range" %
                  (name, key, clamp_min and clamp_min(), clamp_max and clamp_max()))
            continue
        check(clamp_min is not None, "%s.%s: a range in the XML, no clamp in the filter" % (name, key))
        if clamp_min is None:
            continue
        cmin, cmax = clamp_min(), clamp_max()
        if lo is not None:
            check(float(lo) == float(cmin), "%s.%s: XML min %r, filter clamps at %r" % (name, key, lo, cmin))
        if hi is not None:
            check(float(hi) == float(cmax), "%s.%s: XML max %r, filter clamps at %r" % (name, key, hi, cmax))
        else:
            check(float(cmax) in (float(VTK_INT_MAX), float(VTK_ID_MAX), VTK_DOUBLE_MAX),
                  "%s.%s: the XML has no max, the filter clamps at %r" % (name, key, cmax))
    parameters = {k: v for k, v in props.items() if k not in ("FileName",)}
    if cls in by_class:
        first_name, first = by_class[cls]
        check(first == parameters, "%s and %s differ: %s" %
              (first_name, name, set(first.items()) ^ set(parameters.items())))
    else:
        by_class[cls] = (name, parameters)

# The statistics reach ParaView: a run forced out of core fills the information properties.
from paraview.simple import Sphere  # noqa: E402 (SIPMSSDecimate: from LoadPlugin)

sphere = Sphere(ThetaResolution=64, PhiResolution=64)
dec = SIPMSSDecimate(Input=sphere, TargetNumberOfTriangles=500, MemoryBudgetMB=1,
                     OperationMode=2)
dec.UpdatePipeline()
dec.UpdatePropertyInformation()
algorithm = dec.GetClientSideObject()
check(algorithm.GetUsedOutOfCore(), "the run was not out of core")
for key in STATISTICS:
    got = dec.GetProperty(key).GetData()
    want = getattr(algorithm, "Get" + key)()
    check(float(got) == float(want), "information property %s = %r, filter %r" % (key, got, want))
check(dec.GetProperty("OutputTriangles").GetData() <= 500 < dec.GetProperty("InputTriangles").GetData(),
      "triangle counts: %r -> %r" % (dec.GetProperty("InputTriangles").GetData(),
                                    dec.GetProperty("OutputTriangles").GetData()))
check(dec.GetProperty("PeakTemporaryFileBytes").GetData() > 0, "no block file bytes out of core")
check(0 < dec.GetProperty("AchievedError").GetData() < 1, "achieved error %r" %
      dec.GetProperty("AchievedError").GetData())
check(abs(dec.GetProperty("ErrorDiagonal").GetData() - 3 ** 0.5) < 0.01, "diagonal %r" %
      dec.GetProperty("ErrorDiagonal").GetData())  # (the unit sphere's box: side 1)
check(dec.GetProperty("GridDimension").GetData() == 0, "a decimation reports a grid")
# Two-stage on the automatic grid (-1): the grid it ran on is reported (300 for this target).
dec.PreClusterGridDimension = -1
dec.UpdatePipeline()
dec.UpdatePropertyInformation()
check(dec.GetProperty("GridDimension").GetData() == 300,
      "two-stage's automatic grid %r" % dec.GetProperty("GridDimension").GetData())
check(dec.GetProperty("OutputTriangles").GetData() <= 500, "two-stage's triangles %r" %
      dec.GetProperty("OutputTriangles").GetData())

for e in errors:
    print("FAIL:", e)
print("checked %d proxies" % len(PROXIES))
sys.exit(1 if errors else 0)
