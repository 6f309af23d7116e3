#!/usr/bin/env bash
# A/B timing of two builds of mpg's core on one scene at a fixed spp, the two
# interleaved in one run (a ratio holds on a noisy machine), and whether the
# two images are bit-identical (a change meant to keep the same random numbers).
#
#   cp .venv/lib/python3.11/site-packages/mpg/_core*.so /tmp/core_a.so   # before the change
#   ... rebuild ...
#   cp .venv/lib/python3.11/site-packages/mpg/_core*.so /tmp/core_b.so
#   bash bench/ab_core.sh /tmp/core_a.so /tmp/core_b.so scenes/eval/sphere.xml 256 5 --integrator path
#
# Writes bench/results/ab_core.txt (appends); leaves core B installed.
set -euo pipefail
cd "$(dirname "$0")/.."
a=$1; b=$2; scene=$3; spp=$4; rep=$5; shift 5
so=$(ls .venv/lib/python3.11/site-packages/mpg/_core*.so)
out=bench/results/ab_core.txt
mkdir -p bench/results
tmp=$(mktemp -d)
ta=(); tb=()
# Swap cores by rename, never by writing over the installed file: a process
# that still maps it (a render of the other core being torn down, an editor's
# language server) would see its code change under it.
swap_core() { cp "$1" "$so.swap" && mv -f "$so.swap" "$so"; }
for r in $(seq "$rep"); do
  for v in a b; do
    if [ $v = a ]; then swap_core "$a"; else swap_core "$b"; fi
    .venv/bin/mpg-render "$scene" --spp "$spp" --threads 2 -q --no-preview -o "$tmp/$v.exr" \
        --stats "$tmp/$v.json" "$@" >/dev/null
    t=$(.venv/bin/python -c "import json,sys; print(json.load(open(sys.argv[1]))['seconds'])" "$tmp/$v.json")
    if [ $v = a ]; then ta+=("$t"); else tb+=("$t"); fi
  done
done
swap_core "$b"
.venv/bin/python - "$tmp" "$scene $spp spp $*" "${ta[*]}" "${tb[*]}" <<'PY' | tee -a "$out"
import sys, statistics, numpy as np, OpenEXR, Imath
tmp, what, ta, tb = sys.argv[1:5]
ta = [float(x) for x in ta.split()]; tb = [float(x) for x in tb.split()]
def rd(p):
    f = OpenEXR.InputFile(p)
    return [np.frombuffer(f.channel(c, Imath.PixelType(Imath.PixelType.FLOAT)), np.float32) for c in "RGB"]
same = all(np.array_equal(x, y) for x, y in zip(rd(f"{tmp}/a.exr"), rd(f"{tmp}/b.exr")))
ma, mb = statistics.median(ta), statistics.median(tb)
print(f"{what}: A median {ma:.3f} s (best {min(ta):.3f}), B median {mb:.3f} s (best {min(tb):.3f}), "
      f"B/A {mb / ma:.3f} (best {min(tb) / min(ta):.3f}), images identical: {same}")
PY
rm -rf "$tmp"
