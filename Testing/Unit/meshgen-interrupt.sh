#!/usr/bin/env bash
# sipmss-meshgen stopped by a signal leaves nothing behind: `subdivide` (out of core) stops at its
# next chunk, removes its block files and its unfinished output and exits 128 + the signal;
# `scan --order rings`, stopped while it writes, removes its unfinished output. A finished run
# leaves its output alone, under its own name.
#   meshgen-interrupt.sh SIPMSS_MESHGEN
set -euo pipefail
meshgen="$1"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/sipmss-meshgen-interrupt-XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
mkdir "$tmp/blocks" "$tmp/out"
fail() { echo "FAIL: $*"; ls -la "$tmp/blocks" "$tmp/out"; exit 1; }
# Waits (30 s at most) until the glob $1 matches a file.
await() {
  for _ in $(seq 300); do
    compgen -G "$1" >/dev/null && return 0
    sleep 0.1
  done
  fail "nothing matched $1"
}
# Sends SIGTERM to $1 and checks it exits 143 (128 + 15), leaving nothing in the output directory.
stop() {
  kill -TERM "$1"
  local rc=0
  wait "$1" || rc=$?
  [ "$rc" = 143 ] || fail "$2 exited $rc, not 143"
  [ -z "$(ls -A "$tmp/out")" ] || fail "$2 left an output"
}

"$meshgen" scan "$tmp/in.ply" --triangles 20000 >/dev/null
# A finished run: its output under its own name, nothing else.
"$meshgen" subdivide "$tmp/in.ply" "$tmp/out/done.ply" --levels 1 --memory-mb 0.0625 \
  --tmpdir "$tmp/blocks" >/dev/null
[ -s "$tmp/out/done.ply" ] || fail "no output"
[ -z "$(ls -A "$tmp/blocks")" ] || fail "block files left by a finished run"
[ "$(ls -A "$tmp/out")" = "done.ply" ] || fail "more than the output in its directory"
rm "$tmp/out/done.ply"

# subdivide, 6 levels (80M triangles) at 1 MiB: stopped once its block files exist.
"$meshgen" subdivide "$tmp/in.ply" "$tmp/out/big.ply" --levels 6 --memory-mb 1 \
  --tmpdir "$tmp/blocks" >"$tmp/log" 2>&1 &
pid=$!
await "$tmp/blocks/sipmss-*/*"
stop "$pid" subdivide
grep -q "interrupted; nothing was written" "$tmp/log" || fail "no message: $(cat "$tmp/log")"
[ -z "$(ls -A "$tmp/blocks")" ] || fail "subdivide left block files"

# scan --order rings (400M triangles, written as generated): stopped while it writes.
"$meshgen" scan "$tmp/out/rings.ply" --triangles 400000000 --order rings >/dev/null 2>&1 &
pid=$!
await "$tmp/out/.partial-*"
stop "$pid" scan
echo "meshgen interrupts: nothing left behind"
