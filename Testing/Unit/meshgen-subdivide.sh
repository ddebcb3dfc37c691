#!/usr/bin/env bash
# sipmss-meshgen subdivide within a memory budget: the same bytes at 64 KiB (out of core, block
# files and external sorts) as unbounded (in core); a closed input stays closed (V = 2 + F / 2)
# with 16x its triangles after two levels; the shuffled order is the same surface, the same bytes
# at every budget, and sorted within the budget too (its peak memory that of the scanner order,
# not the mesh's); no temporary file is left behind.
#   meshgen-subdivide.sh SIPMSS SIPMSS_MESHGEN
set -euo pipefail
sipmss="$1" meshgen="$2"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/sipmss-subdivide-XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
mkdir "$tmp/blocks"
"$meshgen" scan "$tmp/in.ply" --triangles 20000 >/dev/null
core="$("$meshgen" subdivide "$tmp/in.ply" "$tmp/core.ply" --levels 2 --memory-mb 0)"
paged="$("$meshgen" subdivide "$tmp/in.ply" "$tmp/paged.ply" --levels 2 --memory-mb 0.0625 \
  --tmpdir "$tmp/blocks")"
"$meshgen" subdivide "$tmp/in.ply" "$tmp/shuffled.ply" --levels 2 --order shuffled --memory-mb 0.0625 \
  --tmpdir "$tmp/blocks" >/dev/null
"$meshgen" subdivide "$tmp/in.ply" "$tmp/shuffled-core.ply" --levels 2 --order shuffled \
  --memory-mb 0 >/dev/null
# Peak RSS (KiB) of both orders at 64 KiB, on a larger mesh (1.3M triangles: 15 MB as arrays).
peak() {
  /usr/bin/time -f "%M" -o "$tmp/peak.txt" "$meshgen" subdivide "$tmp/in.ply" "$tmp/big.ply" \
    --levels 3 --order "$1" --memory-mb 0.0625 --tmpdir "$tmp/blocks" >/dev/null
  cat "$tmp/peak.txt"
}
peak_scanner="$(peak scanner)" peak_shuffled="$(peak shuffled)"
rm -f "$tmp/big.ply"
# Many vertices and few faces (the budget's estimate must count the vertices too).
/usr/bin/python3 - "$tmp/few.ply" <<'PY'
import struct, sys
nv = 300000
with open(sys.argv[1], "wb") as f:
    f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\n"
             "property float y\nproperty float z\nelement face 10\n"
             "property list uchar int vertex_indices\nend_header\n" % nv).encode())
    f.write(b"".join(struct.pack("<3f", i * 1e-3, (i % 7) * 1e-2, (i % 13) * 1e-2) for i in range(nv)))
    for t in range(10):
        f.write(struct.pack("<B3i", 3, 3 * t, 3 * t + 1, 3 * t + 2))
PY
"$meshgen" subdivide "$tmp/few.ply" "$tmp/few-core.ply" --memory-mb 0 >/dev/null
"$meshgen" subdivide "$tmp/few.ply" "$tmp/few-2mb.ply" --memory-mb 2 --tmpdir "$tmp/blocks" >/dev/null
status=0
fail() { echo "FAIL: $*"; status=1; }
cmp "$tmp/few-core.ply" "$tmp/few-2mb.ply" || fail "many vertices: in core and at 2 MB differ"
case "$core" in *"(in core"*) ;; *) fail "unbounded did not run in core: $core" ;; esac
case "$paged" in *"(out of core"*) ;; *) fail "64 KiB did not run out of core: $paged" ;; esac
cmp "$tmp/core.ply" "$tmp/paged.ply" || fail "in core and out of core differ"
cmp "$tmp/shuffled-core.ply" "$tmp/shuffled.ply" || fail "shuffled: in core and out of core differ"
cmp -s "$tmp/core.ply" "$tmp/shuffled.ply" && fail "the shuffled output is in scanner order"
[ "$peak_shuffled" -le $((peak_scanner + 4096)) ] ||
  fail "shuffled peak RSS ${peak_shuffled} KiB, scanner order ${peak_scanner} KiB (over 4 MiB more)"
echo "peak RSS at 64 KiB, 1.3M triangles: scanner ${peak_scanner} KiB, shuffled ${peak_shuffled} KiB"
[ -z "$(ls -A "$tmp/blocks")" ] || fail "temporary files left: $(ls -A "$tmp/blocks")"
# The input is never its own output (also through a symbolic link): an error, the file intact.
cp "$tmp/in.ply" "$tmp/keep.ply"
ln -s "$tmp/in.ply" "$tmp/link.ply"
if "$meshgen" subdivide "$tmp/in.ply" "$tmp/link.ply" 2>"$tmp/err.txt"; then
  fail "subdividing into the input succeeded"
fi
grep -q "is the input file" "$tmp/err.txt" || fail "no clear error: $(cat "$tmp/err.txt")"
cmp "$tmp/in.ply" "$tmp/keep.ply" || fail "the input was changed"
/usr/bin/python3 - "$sipmss" "$tmp" <<'PY' || status=1
import json, subprocess, sys
sipmss, tmp = sys.argv[1], sys.argv[2]
def info(name):
    return json.loads(subprocess.run([sipmss, "info", "%s/%s.ply" % (tmp, name)],
                                     capture_output=True, text=True, check=True).stdout)
src, out, shuffled = info("in"), info("core"), info("shuffled")
ok = True
def check(cond, what):
    global ok
    if not cond:
        print("FAIL:", what)
        ok = False
check(out["triangles"] == 16 * src["triangles"], "triangles %d, input %d" % (out["triangles"], src["triangles"]))
check(src["vertices"] == 2 + src["triangles"] // 2, "the input is not closed: %r" % src)
check(out["vertices"] == 2 + out["triangles"] // 2, "the output is not closed: %r" % out)
check(shuffled["vertices"] == out["vertices"] and shuffled["triangles"] == out["triangles"],
      "shuffled counts %r" % shuffled)
d = json.loads(subprocess.run([sipmss, "compare", "%s/core.ply" % tmp, "%s/shuffled.ply" % tmp],
                              capture_output=True, text=True, check=True).stdout)
check(d["hausdorff"] < 1e-6, "the shuffled output is another surface: %r" % d)
src_bounds, out_bounds = src["bounds"], out["bounds"]
check(all(abs(a - b) < 0.05 for a, b in zip(src_bounds, out_bounds)), "bounds %r -> %r" % (src_bounds, out_bounds))
print("ok" if ok else "")
sys.exit(0 if ok else 1)
PY
exit "$status"
