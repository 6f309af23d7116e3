"""bench/swap_maps.py: one training's maps with parts of another's swapped
in. A variant takes the parts it names from the long training and the rest
from the short one, and the script writes a summary of a tiny scene's
renders."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from bench_util import bench_module
from mpg.chain_rates import DeltaSplitRefiner

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def swap_maps():
    return bench_module("swap_maps")


class _Refiner(DeltaSplitRefiner):   # (the held-out check's attributes glass_maps reads, its maps())
    def __init__(self, shape):
        self.branched = True
        self.glass = np.zeros(shape, dtype=bool)
        self.glass[:2] = True
        self.glass_map = np.where(self.glass, 2.0, 1.0).astype(np.float32)
        self.plain = np.zeros(shape, dtype=bool)
        self.plain[0] = True
        self.base = np.ones(shape, dtype=np.float32)   # (the training's split: one pixel at 3)
        self.base[0, 0] = 3.0


def _seen(tag: float, shape=(6, 6)) -> dict:
    keys = ["chain_rate_map", "guided_trace_map", "deep_rate_map", "pixel_split_map", "delta_split_map",
            "delta_branch_map"]
    kw = {k: np.full(shape, tag + i, dtype=np.float32) for i, k in enumerate(keys)}
    kw.update(spp=None, time=3.0, seed=0, sampler="independent", pixel_split_refine=print, delta_split_refine=print)
    return {"kw": kw, "integrator": {"type": "mpg", "guide": f"guide{tag}", "delta_branch": 8},
            "delta_refiner": _Refiner(shape)}


def test_a_variant_swaps_the_parts_it_names_and_nothing_else(swap_maps):
    short, long = _seen(10.0), _seen(20.0)
    for name, moved in [("short", set()), ("short+guide", {"guide"}), ("short+rates", {"chain_rate_map"}),
                        ("short+delta_split", {"delta_split_map", "delta_branch_map"}),
                        ("short+pixel_split+traces+deep", {"pixel_split_map", "guided_trace_map", "deep_rate_map"})]:
        call = swap_maps.variant_call(name, short, long)
        assert call["integrator"]["guide"] == ("guide20.0" if "guide" in moved else "guide10.0"), name
        for k, v in short["kw"].items():
            if isinstance(v, np.ndarray):
                want = long["kw"][k] if k in moved else v
                assert np.array_equal(call[k], want), (name, k)
        # (the maps held fixed: no refinement or check between the passes, no time limit)
        assert call["pixel_split_refine"] is None and call["delta_split_refine"] is None and call["time"] is None
    # path: the peer at the same sampler, without the trainings' guide or maps
    p = swap_maps.variant_call("path", short, long)
    assert p["integrator"] == "path" and p["sampler"] == "independent" and p["time"] is None
    assert not any(isinstance(v, np.ndarray) for v in p.values())
    long_call = swap_maps.variant_call("long", short, long)
    assert long_call["integrator"]["guide"] == "guide20.0"
    assert all(np.array_equal(long_call[k], v) for k, v in long["kw"].items() if isinstance(v, np.ndarray))
    # glass: every glass pixel split at least twice, plain paths where the check's are
    g = swap_maps.variant_call("short+glass", short, long)
    assert np.array_equal(g["delta_split_map"], short["delta_refiner"].glass_map)
    assert np.array_equal(g["delta_branch_map"] == 0, short["delta_refiner"].plain)
    assert np.array_equal(g["chain_rate_map"], short["kw"]["chain_rate_map"])
    # grow<R>: the glass split only within R pixels of a pixel the training split
    d = short["delta_refiner"]
    d.glass_map = np.where(d.glass, np.maximum(d.base, 2.0), d.base).astype(np.float32)
    g1 = swap_maps.variant_call("short+grow1", short, long)["delta_split_map"]
    want = d.base.copy()
    want[:2, :2] = np.maximum(want[:2, :2], 2.0)   # (glass rows 0-1, columns 0-1 near (0, 0))
    assert np.array_equal(g1, want)
    assert np.array_equal(swap_maps.variant_call("short+grow9", short, long)["delta_split_map"], d.glass_map)
    # glassplain: the glass split's new pixels with plain paths, the training's own as the check has them
    gp = swap_maps.variant_call("short+glassplain", short, long)
    assert np.array_equal(gp["delta_split_map"], d.glass_map)
    new = (d.glass_map > 1) & (d.base <= 1)
    assert np.all(gp["delta_branch_map"][new] == 0) and gp["delta_branch_map"][0, 0] == 0   # ((0, 0): plain in d)
    assert np.all(gp["delta_branch_map"][~new & ~d.plain] == 1)
    for bad in ["long+guide", "path+guide", "short+nothing", "short+guide+guide", "short+glass+delta_split", "medium",
                "short+grow0", "short+grow2+glass", "short+glassplain+glass"]:
        with pytest.raises(ValueError):
            swap_maps.parse_variant(bad)
    with pytest.raises(ValueError):   # (a training without the check has no glass split)
        swap_maps.variant_call("short+glass", {k: v for k, v in short.items() if k != "delta_refiner"}, long)


def test_the_script_writes_its_summary(tmp_path):
    dest = tmp_path / "sm.json"
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "swap_maps.py"), str(ROOT / "scenes" / "sphere_glass.xml"),
                          "--param", "res=16", "--short", "0.5", "--long", "1.5", "--spp", "4", "--seeds", "2",
                          "--variants", "short", "long", "short+delta_split+guide", "--out", str(dest)],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    assert d["seeds"] == 2 and d["spp"] == 4
    assert d["training_spp"]["long"] > d["training_spp"]["short"] >= 2
    assert abs(sum(d["group_fraction"].values()) - 1.0) < 1e-9
    assert set(d["variants"]) == {"short", "long", "short+delta_split+guide"}
    for r in d["variants"].values():
        assert np.isfinite(r["variance"]) and r["variance"] > 0 and r["seconds_median"] > 0
    bad = subprocess.run([sys.executable, str(ROOT / "bench" / "swap_maps.py"), "sphere", "--variants", "short+x"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown part 'x'" in bad.stderr
