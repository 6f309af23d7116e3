"""bench/fixed_maps.py: the learned maps held fixed and varied. Its variants
change the maps they name and nothing else, and the script writes a summary
of a tiny scene's renders."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from bench_util import bench_module

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fixed_maps():
    return bench_module("fixed_maps")


def test_the_variants_change_only_the_maps_they_name(fixed_maps):
    rng = np.random.default_rng(3)
    q = rng.choice([0.0, 0.125, 1.0], (24, 24)).astype(np.float32)
    g = np.where(q > 0, 0.0, rng.choice([0.0, 1.0, 4.0], (24, 24))).astype(np.float32)
    est, pt, tr = q > 0, (q <= 0) & (g <= 0), (q <= 0) & (g > 0)
    assert est.any() and pt.any() and tr.any()
    assert fixed_maps.variant_maps("learned", q, g) == {}
    m = fixed_maps.variant_maps("est1", q, g)
    assert set(m) == {"chain_rate_map"}
    assert np.all(m["chain_rate_map"][est] == 1.0) and np.array_equal(m["chain_rate_map"][~est], q[~est])
    m = fixed_maps.variant_maps("all3", q, g)
    assert np.all(m["chain_rate_map"] == 0.0) and np.all(m["guided_trace_map"] == 3.0)
    assert np.array_equal(m["deep_rate_map"], np.where(q > 0, q, 1.0))   # (handoff_all's later separators)
    assert "deep_rate_map" not in fixed_maps.variant_maps("all3", q, g, deep=0.0)
    assert np.array_equal(fixed_maps.variant_maps("all3", q, g, deep=0.5)["deep_rate_map"],
                          np.where(q > 0, np.minimum(q, 0.5), 0.5))
    m = fixed_maps.variant_maps("est-traced2", q, g)
    assert np.all(m["chain_rate_map"] == 0.0)
    assert np.all(m["guided_trace_map"][est] == 2.0) and np.array_equal(m["guided_trace_map"][~est], g[~est])
    m = fixed_maps.variant_maps("pt-traced4", q, g)
    assert set(m) == {"guided_trace_map"}
    assert np.all(m["guided_trace_map"][pt] == 4.0) and np.array_equal(m["guided_trace_map"][~pt], g[~pt])
    with pytest.raises(ValueError):
        fixed_maps.variant_maps("all", q, g)
    # pixels without chain work (rate 1 by the rates' rule) keep their rate
    chain = rng.random((24, 24)) < 0.7
    m = fixed_maps.variant_maps("est-traced2", q, g, chain)
    moved = est & chain
    assert moved.any() and (est & ~chain).any()
    assert np.all(m["chain_rate_map"][moved] == 0.0) and np.array_equal(m["chain_rate_map"][~moved], q[~moved])
    assert np.all(m["guided_trace_map"][moved] == 2.0) and np.array_equal(m["guided_trace_map"][~moved], g[~moved])
    m = fixed_maps.variant_maps("est1", q, g, chain)
    assert np.array_equal(m["chain_rate_map"][est & ~chain], q[est & ~chain])
    assert [fixed_maps.traces_of(v) for v in ("learned", "est1", "all0", "all12", "est-traced4", "pt-traced2")] == \
        [0, 0, 0, 12, 4, 2]


def test_the_script_writes_its_summary(tmp_path):
    dest = tmp_path / "fm.json"
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "fixed_maps.py"), str(ROOT / "scenes" / "sphere_glass.xml"),
                          "--param", "res=16", "--time", "3", "--spp", "4", "--seeds", "2",
                          "--variants", "learned", "all2", "est1", "--out", str(dest)],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    assert d["seeds"] == 2 and d["spp"] == 4
    # (mpg's default pixel split, refined online: each variant's split solved again and refined)
    assert d["online_pixel_split"] is True
    assert abs(sum(d["group_fraction"].values()) - 1.0) < 1e-9
    assert d["group_fraction"]["no chain work"] < 1.0   # (the glass sphere's caustic: chain work)
    assert set(d["variants"]) == {"learned", "all2", "est1"}
    for r in d["variants"].values():
        assert np.isfinite(r["variance"]) and r["variance"] > 0 and r["seconds_median"] > 0
        # the groups partition the image
        assert abs(sum(r["group_variance"].values()) - r["variance"]) <= 1e-9 * max(1.0, r["variance"])
    bad = subprocess.run([sys.executable, str(ROOT / "bench" / "fixed_maps.py"), "sphere", "--variants", "most"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown variant" in bad.stderr
    for args, why in ((["--variants", "all2", "all2"], "twice"), (["--variants", "all65"], "at most 64"),
                      (["--params", '{"handoff_guided": 0}', "--variants", "learned", "all2"], "handoff_guided")):
        bad = subprocess.run([sys.executable, str(ROOT / "bench" / "fixed_maps.py"), "sphere"] + args,
                             capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and why in bad.stderr, (args, bad.stderr)
