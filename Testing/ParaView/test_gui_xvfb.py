"""The ParaView GUI with the SIPMSS plugin, driven under Xvfb as a user would drive it.

Writes a PLY mesh, starts the real `paraview` under `xvfb-run -a` with the plugin on
PV_PLUGIN_PATH and plays test_gui_xvfb.xml.in (QtTesting events: menus, File > Open, the
properties panel, Apply). gui_checks.py, run in the GUI's Python shell, records each result;
this script then checks them: every proxy was made from the menu it should be in, holds the
values typed into the panel, and gives the triangle count of the same VTK filter run with the
same settings outside ParaView; the decimations end at or below the typed target. The Lock Array
chosen in a drop-down of the file's vertex properties keeps its vertices where they were.

Exit 77 (ctest SKIP_RETURN_CODE) when xvfb-run is missing or the X server cannot start.

usage: test_gui_xvfb.py PARAVIEW PLUGIN_DIR OUT_DIR [SCREENSHOT_DIR]
  OUT_DIR gets results.json, paraview.log and the screenshots (paraview-panel.png: the whole
  window with the SIPMSS Decimate panel; paraview-result.png: the render view); with
  SCREENSHOT_DIR they are copied there too (e.g. docs/images).
"""
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile

SKIP = 77
HERE = os.path.dirname(os.path.abspath(__file__))
SCREEN = "-screen 0 1280x800x24 -br -nocursor"
TIMEOUT = 600


def write_ply(path, nu=120, nv=80):
    """A bumpy torus, binary PLY: 2*nu*nv triangles, closed, no two faces alike, with a vertex
    property "keep"."""
    points = []
    for i in range(nu):
        u = 2 * math.pi * i / nu
        for j in range(nv):
            v = 2 * math.pi * j / nv
            r = 0.4 + 0.05 * math.sin(5 * u) * math.cos(3 * v)
            points.append(((1 + r * math.cos(v)) * math.cos(u),
                           (1 + r * math.cos(v)) * math.sin(u), r * math.sin(v)))
    faces = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            faces += [(a, b, c), (a, c, d)]
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\n"
                 "property float x\nproperty float y\nproperty float z\nproperty uchar keep\n"
                 "element face %d\nproperty list uchar int vertex_indices\nend_header\n" %
                 (len(points), len(faces))).encode())
        for k, p in enumerate(points):
            # "keep": a vertex property the SIPMSS Decimate File Reader's Lock Array lists
            # (10 vertices, so that the decimation still reaches its target)
            f.write(struct.pack("<3fB", *p, 1 if k < nv and k % 8 == 0 else 0))
        for t in faces:
            f.write(struct.pack("<B3i", 3, *t))
    return len(faces)


def run(cmd, env, log_path):
    """Run `cmd` in its own process group; kill the whole group (Xvfb too) on timeout."""
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            return proc.wait(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
            return None


def main():
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    paraview, plugin_dir, out = sys.argv[1:4]
    shots = sys.argv[4] if len(sys.argv) == 5 else None
    if not os.path.isfile(os.path.join(plugin_dir, "SIPMSS.so")):
        sys.exit("no SIPMSS.so in %s" % plugin_dir)
    xvfb_run = shutil.which("xvfb-run")
    if not xvfb_run:
        print("SKIPPED: xvfb-run is not installed (scripts/setup installs xvfb and xauth)")
        return SKIP
    os.makedirs(out, exist_ok=True)
    for name in ("results.json", "paraview-panel.png", "paraview-result.png"):
        if os.path.exists(os.path.join(out, name)):
            os.remove(os.path.join(out, name))

    with tempfile.TemporaryDirectory(prefix="sipmss-gui-") as tmp:
        env = dict(os.environ)
        runtime = os.path.join(tmp, "runtime")
        os.mkdir(runtime, 0o700)
        env.update(XDG_RUNTIME_DIR=runtime, XDG_CONFIG_HOME=os.path.join(tmp, "config"),
                   PYTHONDONTWRITEBYTECODE="1",  # no __pycache__ in the source tree
                   PV_PLUGIN_PATH=plugin_dir, SIPMSS_GUI_OUT=os.path.abspath(out))

        # Can an X server start here at all?
        probe = run([xvfb_run, "-a", "-s", SCREEN, "true"], env, os.path.join(tmp, "probe.log"))
        if probe != 0:
            with open(os.path.join(tmp, "probe.log")) as f:
                print("SKIPPED: xvfb-run could not start an X server:\n" + f.read())
            return SKIP

        ply = os.path.join(tmp, "mesh.ply")
        n_input = write_ply(ply)
        fbdir = os.path.join(tmp, "fb")
        os.mkdir(fbdir)
        env.update(SIPMSS_GUI_PLY=ply, SIPMSS_GUI_FBDIR=fbdir)
        with open(os.path.join(HERE, "test_gui_xvfb.xml.in")) as f:
            events = f.read().replace("@PLY@", ply).replace("@CHECKS_DIR@", HERE)
        script = os.path.join(tmp, "events.xml")
        with open(script, "w") as f:
            f.write(events)

        log_path = os.path.join(out, "paraview.log")
        cmd = [xvfb_run, "-a", "-s", "%s -fbdir %s" % (SCREEN, fbdir),
               paraview, "--dr", "--test-script=" + script, "--exit"]
        print(" ".join(cmd))
        rc = run(cmd, env, log_path)
    with open(log_path, errors="replace") as f:
        log = f.read()
    if rc is None:
        sys.exit("paraview did not finish in %d s; log:\n%s" % (TIMEOUT, log[-4000:]))
    if "Xvfb failed to start" in log:
        print("SKIPPED: Xvfb failed to start:\n" + log[-2000:])
        return SKIP

    errors = []
    if rc != 0:
        errors.append("paraview exited with %d (an event could not be played?)" % rc)
    try:
        with open(os.path.join(out, "results.json")) as f:
            results = json.load(f)
    except (OSError, ValueError) as e:
        results = {"checks": [], "errors": []}
        errors.append("no results from the GUI: %s" % e)
    errors += results["errors"]
    if results.get("finished") is not True and not errors:
        errors.append("the event script did not reach its end")
    want = {"SIPMSSCluster", "SIPMSSDecimate", "SIPMSSDecimateFile", "SIPMSSClusterFile",
            "SIPMSSDecimateFileReader"}
    seen = set()
    locked = [check for check in results["checks"] if "locked" in check]
    if [check["locked"] for check in locked] != ["keep"]:
        errors.append("the vertices locked by the Lock Array chosen in the panel were not "
                      "checked: %s" % locked)
    for check in locked:
        print("Lock Array %r chosen in the panel: its %d vertices are in the output" %
              (check["locked"], check["vertices"]))
    for check in results["checks"]:
        if "locked" in check:
            continue
        seen.add(check["proxy"])
        got, expected = check["triangles"], check["expected"]
        if check["input_triangles"] != n_input:
            errors.append("%s: input has %d triangles, the file %d" %
                          (check["proxy"], check["input_triangles"], n_input))
        if got != expected:
            errors.append("%s %s: %d triangles in the GUI, %d from the VTK filter" %
                          (check["proxy"], check["settings"], got, expected))
        if not 0 < got < n_input:
            errors.append("%s: %d triangles from %d" % (check["proxy"], got, n_input))
        target = check["settings"].get("TargetNumberOfTriangles")
        if target is not None and got > target:
            errors.append("%s: %d triangles, above the target %d typed in the panel" %
                          (check["proxy"], got, target))
        print("%-26s %-34s %6d -> %5d triangles (VTK: %d)" %
              (check["proxy"], check["settings"], n_input, got, expected))
    if seen != want:
        errors.append("checked %s; missing %s" % (sorted(seen), sorted(want - seen)))
    for name in ("paraview-panel.png", "paraview-result.png"):
        path = os.path.join(out, name)
        if not os.path.isfile(path) or os.path.getsize(path) < 1000:
            errors.append("no screenshot %s" % path)
        elif shots:
            os.makedirs(shots, exist_ok=True)
            shutil.copy(path, os.path.join(shots, name))
    if errors:
        print("FAILED:\n  " + "\n  ".join(errors))
        print("paraview log (%s), last lines:\n%s" % (log_path, log[-4000:]))
        return 1
    print("ParaView GUI test passed; screenshots in %s" % (shots or out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
