"""Checks run inside the ParaView GUI's Python shell by test_gui_xvfb.py's event script.

The event script drives the GUI (menus, File > Open, the properties panel, Apply); these
functions only look at the result: the active source is the proxy the GUI made, its
properties hold what was typed into the panel, and its output has the triangle count that the
same VTK filter with the same settings gives outside ParaView. Results go to
$SIPMSS_GUI_OUT/results.json, which the driver checks after ParaView exits. Screenshots of the
whole screen come from the Xvfb frame buffer ($SIPMSS_GUI_FBDIR/Xvfb_screen0, an XWD file).
"""
import json
import os
import struct
import traceback
import zlib

from paraview.simple import (GetActiveSource, GetActiveViewOrCreate, Render, ResetCamera,
                             SaveScreenshot, SetActiveSource, FindSource, Show, Hide)

_OUT = os.environ["SIPMSS_GUI_OUT"]
_PLY = os.environ["SIPMSS_GUI_PLY"]
_results = {"checks": [], "errors": []}
try:
    import sipmss  # noqa: F401 (wraps the client-side objects as vtkSIPMSS* classes)
except ImportError:
    _results["errors"].append("import sipmss in the GUI's Python (PYTHONPATH=%s): %s" %
                              (os.environ.get("PYTHONPATH"), traceback.format_exc()))


def _save():
    with open(os.path.join(_OUT, "results.json"), "w") as f:
        json.dump(_results, f, indent=1)


def _triangles(dataset):
    n = dataset.GetNumberOfPolys()
    it = dataset.GetPolys()
    # every cell a triangle: connectivity is 3 per cell
    assert it.GetNumberOfConnectivityIds() == 3 * n, "non-triangle cells in the output"
    return n


def _reference(cls, settings, from_file):
    """The same filter with the same settings, run by VTK in this process, without ParaView."""
    from vtkmodules.vtkIOPLY import vtkPLYReader
    f = getattr(sipmss, cls)()
    if from_file:
        f.SetFileName(_PLY)
    else:
        reader = vtkPLYReader()
        reader.SetFileName(_PLY)
        f.SetInputConnection(reader.GetOutputPort())
    for name, value in settings.items():
        getattr(f, "Set" + name)(value)
    f.Update()
    return _triangles(f.GetOutput())


def check_active(xml_name, settings, from_file=False):
    """The active source is a fresh `xml_name` proxy whose properties are `settings` (typed in the
    panel) and whose output matches the VTK filter's."""
    try:
        src = GetActiveSource()
        got_name = src.GetXMLName() if src else None
        if got_name != xml_name:
            raise AssertionError("active source is %s, expected %s" % (got_name, xml_name))
        for name, value in settings.items():
            if src.GetPropertyValue(name) != value:
                raise AssertionError("%s.%s = %r, but %r was typed in the panel" %
                                     (xml_name, name, src.GetPropertyValue(name), value))
        if from_file and src.GetPropertyValue("FileName") != _PLY:
            raise AssertionError("%s.FileName = %r" % (xml_name, src.GetPropertyValue("FileName")))
        algorithm = src.GetClientSideObject()
        for name, value in settings.items():  # the setter got it (an int for a vtkIdType)
            if getattr(algorithm, "Get" + name)() != value:
                raise AssertionError("%s: Get%s() = %r after the panel set %r" %
                                     (algorithm.GetClassName(), name,
                                      getattr(algorithm, "Get" + name)(), value))
        data = algorithm.GetOutputDataObject(0)
        got = _triangles(data)
        want = _reference("vtk" + xml_name.replace("FileReader", "").replace("File", ""),
                          settings, from_file)
        entry = {"proxy": xml_name, "settings": settings, "from_file": from_file,
                 "triangles": got, "expected": want,
                 "input_triangles": _input_triangles()}
        _results["checks"].append(entry)
        print("SIPMSS GUI check:", entry)
    except Exception:  # recorded, and the driver fails on it
        _results["errors"].append(traceback.format_exc())
        print(traceback.format_exc())
    _save()


_n_input = []


def _input_triangles():
    if not _n_input:
        from vtkmodules.vtkIOPLY import vtkPLYReader
        reader = vtkPLYReader()
        reader.SetFileName(_PLY)
        reader.Update()
        _n_input.append(_triangles(reader.GetOutput()))
    return _n_input[0]


def select(name):
    """Make the pipeline source registered as `name` active (as a click in the Pipeline Browser)."""
    src = FindSource(name)
    if src is None:
        _results["errors"].append("no pipeline source named %r" % name)
        _save()
    SetActiveSource(src)


def show_only_active(edges=True):
    """Show the active source alone (surface with edges) in the render view."""
    view = GetActiveViewOrCreate("RenderView")
    active = GetActiveSource()
    from paraview.simple import GetSources
    for src in GetSources().values():
        if src is not active:
            Hide(src, view)
    display = Show(active, view)
    display.SetRepresentationType("Surface With Edges" if edges else "Surface")
    view.OrientationAxesVisibility = 0
    view.CameraPosition = [1.2, -3.2, 2.0]
    view.CameraFocalPoint = [0, 0, 0]
    view.CameraViewUp = [0, 0, 1]
    ResetCamera(view)
    view.GetActiveCamera().Dolly(1.5)
    Render(view)


def save_view(filename, width=640, height=400):
    """A screenshot of the render view alone."""
    view = GetActiveViewOrCreate("RenderView")
    SaveScreenshot(os.path.join(_OUT, filename), view, ImageResolution=[width, height])


def _read_xwd(path):
    """(width, height, rgb bytes) of the Xvfb frame buffer (an XWD file, header big-endian)."""
    with open(path, "rb") as f:
        data = f.read()
    fields = struct.unpack(">25I", data[:100])
    header_size, version = fields[0], fields[1]
    if version != 7:
        raise ValueError("%s: not an XWD version 7 file" % path)
    width, height = fields[4], fields[5]
    byte_order, bits_per_pixel, bytes_per_line = fields[7], fields[11], fields[12]
    masks = fields[14:17]
    ncolors = fields[19]
    if bits_per_pixel != 32:
        raise ValueError("%s: %d bits per pixel; run Xvfb with -screen 0 WxHx24" %
                         (path, bits_per_pixel))
    offset = header_size + 12 * ncolors
    fmt = "<" if byte_order == 0 else ">"
    rows = []
    shifts = [(m, (m & -m).bit_length() - 1) for m in masks]
    for y in range(height):
        line = data[offset + y * bytes_per_line: offset + y * bytes_per_line + 4 * width]
        pixels = struct.unpack(fmt + "%dI" % width, line)
        row = bytearray(3 * width)
        for c, (mask, shift) in enumerate(shifts):
            row[c::3] = bytes(((p & mask) >> shift) & 0xFF for p in pixels)
        rows.append(bytes(row))
    return width, height, rows


def _write_png(path, width, height, rows):
    def chunk(tag, payload):
        return (struct.pack(">I", len(payload)) + tag + payload +
                struct.pack(">I", zlib.crc32(tag + payload) & 0xFFFFFFFF))
    raw = b"".join(b"\x00" + row for row in rows)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)))
        f.write(chunk(b"IDAT", zlib.compress(raw, 9)))
        f.write(chunk(b"IEND", b""))


def save_screen(filename):
    """A screenshot of the whole X screen: the ParaView window with its panels."""
    try:
        width, height, rows = _read_xwd(os.path.join(os.environ["SIPMSS_GUI_FBDIR"],
                                                     "Xvfb_screen0"))
        # crop to the window: Xvfb runs with a black root window (-br)
        lit = [y for y, row in enumerate(rows) if row.strip(b"\0")]
        rows = rows[lit[0]:lit[-1] + 1]
        left = min(len(row) - len(row.lstrip(b"\0")) for row in rows) // 3
        right = max(len(row.rstrip(b"\0")) + 2 for row in rows) // 3
        rows = [row[3 * left:3 * right] for row in rows]
        _write_png(os.path.join(_OUT, filename), right - left, len(rows), rows)
        _results.setdefault("screenshots", []).append(filename)
    except Exception:
        _results["errors"].append(traceback.format_exc())
        print(traceback.format_exc())
    _save()


def _kept_vertices(name):
    """The positions of the test PLY's vertices whose uchar property `name` is not 0 (the PLY
    test_gui_xvfb.py writes: x, y, z as floats, then `name`)."""
    with open(_PLY, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().split("\n")
    count = int([line for line in header if line.startswith("element vertex")][0].split()[2])
    kept = set()
    for k in range(count):
        x, y, z, flag = struct.unpack_from("<3fB", data, end + 13 * k)
        if flag:
            kept.add((x, y, z))
    return kept


def check_locked(name):
    """Every vertex the active source's Lock Array `name` locks is in its output, unmoved."""
    try:
        data = GetActiveSource().GetClientSideObject().GetOutputDataObject(0)
        points = data.GetPoints()
        out = set(tuple(struct.unpack("<3f", struct.pack("<3f", *points.GetPoint(i))))
                  for i in range(points.GetNumberOfPoints()))
        kept = _kept_vertices(name)
        if not kept or not kept <= out:
            raise AssertionError("%d of the %d vertices locked by %r are not in the output" %
                                 (len(kept - out), len(kept), name))
        _results["checks"].append({"locked": name, "vertices": len(kept)})
    except Exception:
        _results["errors"].append(traceback.format_exc())
        print(traceback.format_exc())
    _save()


def finish():
    _results["finished"] = True
    _save()
    print("SIPMSS GUI checks finished: %d checks, %d errors" %
          (len(_results["checks"]), len(_results["errors"])))


_save()
