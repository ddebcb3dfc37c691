#!/usr/bin/env bash
# Runs decimation, clustering and two-stage with sipmss-checked (the cores built with
# SIPMSS_CHECK_WRITES: a parallel phase's write outside its worker's declared range throws) and
# with sipmss, on a generated scan large enough for every parallel phase: in core on two threads
# and at 8 MB on two (the helper threads on forked DMLs), also with attribute-aware error (its
# per-vertex extensions are written by the same phases). The outputs must be the same bytes.
#   checked-writes.sh SIPMSS SIPMSS_CHECKED SIPMSS_MESHGEN
set -euo pipefail
sipmss="$1" checked="$2" meshgen="$3"
tmp="$(mktemp -d "${TMPDIR:-/tmp}/sipmss-checked-XXXXXX")"
trap 'rm -rf "$tmp"' EXIT
"$meshgen" scan "$tmp/plain.ply" --triangles 600000 >/dev/null
"$meshgen" colorize "$tmp/plain.ply" "$tmp/colored.ply" --cells 6
status=0
input=plain
run() {
  local name="$1"
  shift
  "$sipmss" simplify "$tmp/$input.ply" "$tmp/$name.ply" --quiet "$@"
  if ! "$checked" simplify "$tmp/$input.ply" "$tmp/$name-checked.ply" --quiet "$@"; then
    echo "FAIL: $name: sipmss-checked failed (a write out of its declared range?)"
    status=1
    return
  fi
  if cmp -s "$tmp/$name.ply" "$tmp/$name-checked.ply"; then
    echo "ok: $name"
  else
    echo "FAIL: $name: the outputs differ"
    status=1
  fi
}
for threads in 1 2; do
  run "decimate-core-t$threads" --algorithm decimate --target 20000 --memory-mb unbounded --threads "$threads"
  run "decimate-8mb-t$threads" --algorithm decimate --target 20000 --memory-mb 8 --threads "$threads"
done
run "lods-8mb" --algorithm decimate --reduction 0.99 --lods 3 --memory-mb 8 --threads 2
run "two-stage-8mb" --algorithm two-stage --grid 200 --target 5000 --memory-mb 8 --threads 2
run "cluster-8mb" --algorithm cluster --grid 100 --memory-mb 8 --threads 2
input=colored
attributes=(--attributes normals:0.5,colors:1)
run "attributes-core-t2" --algorithm decimate --target 20000 --memory-mb unbounded --threads 2 "${attributes[@]}"
run "attributes-8mb-t2" --algorithm decimate --target 20000 --memory-mb 8 --threads 2 "${attributes[@]}"
run "attributes-two-stage-8mb" --algorithm two-stage --grid 200 --target 5000 --memory-mb 8 --threads 2 "${attributes[@]}"
run "attributes-cluster-8mb" --algorithm cluster --grid 100 --memory-mb 8 --threads 2 "${attributes[@]}"
run "attributes-cluster-core" --algorithm cluster --grid 100 --memory-mb unbounded --threads 2 "${attributes[@]}"
run "attributes-two-stage-core" --algorithm two-stage --grid 200 --target 5000 --memory-mb unbounded --threads 2 "${attributes[@]}"
# (in core and out of core give the same bytes, with and without attributes)
for pair in "decimate-core-t2 decimate-8mb-t2" "attributes-core-t2 attributes-8mb-t2" \
  "attributes-cluster-core attributes-cluster-8mb" "attributes-two-stage-core attributes-two-stage-8mb"; do
  set -- $pair
  if cmp -s "$tmp/$1.ply" "$tmp/$2.ply"; then
    echo "ok: $1 = $2"
  else
    echo "FAIL: $1 and $2 differ"
    status=1
  fi
done
exit "$status"
