"""Smoke run of mpg-bench (reference, compare, curves, costs) on a tiny scene.

scenes/sphere_glass.xml at 24x24 (--param res=24), copied beside a sidecar with a
caustic box; budgets of a fraction of a second, 1-2 seeds. Checks the output
folders (report.md, results.json with finite numbers, PNGs). Mitsuba entries run
when mitsuba is importable and are skipped otherwise. About 20-30 s on 2 cores.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import shutil

import numpy as np
import pytest

from bench_util import bench_module
from mpg.bench import cli, curves, reference, report, runners
from mpg.bench.scenes import BenchError

HAS_MI = importlib.util.find_spec("mitsuba") is not None
INTEGRATORS = ["path"] + (["mitsuba:path", "mitsuba:ptracer"] if HAS_MI else [])
BOX = [0.4, 0.6, 0.8, 0.85]


@pytest.fixture(scope="module")
def env(tmp_path_factory, scenes_dir):
    d = tmp_path_factory.mktemp("bench")
    shutil.copy(scenes_dir / "sphere_glass.xml", d / "tiny.xml")
    (d / "tiny.json").write_text(json.dumps({
        "name": "tiny", "description": "sphere_glass for the smoke test", "chains": ["TT"],
        "caustic_box": BOX, "reference": "mitsuba ptracer+path"}))
    cache = d / "cache"
    args = ["reference", str(d / "tiny.xml"), "--param", "res=24", "--time", "1",
            "--passes", "4", "--cache", str(cache)]
    if not HAS_MI:
        args += ["--method", "mpg"]
    assert cli.main(args) == 0
    return {"dir": d, "scene": str(d / "tiny.xml"), "cache": str(cache)}


def finite_numbers(x, path="results"):
    """Every number in a JSON tree is finite (None allowed for absent values)."""
    if isinstance(x, dict):
        for k, v in x.items():
            finite_numbers(v, f"{path}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            finite_numbers(v, f"{path}[{i}]")
    elif isinstance(x, float):
        assert math.isfinite(x), path


def check_out(out, pngs):
    assert (out / "report.md").is_file()
    text = (out / "report.md").read_text()
    assert "mpg-bench" in text
    data = json.loads((out / "results.json").read_text())
    finite_numbers(data)
    for p in pngs:
        assert (out / p).is_file() and (out / p).stat().st_size > 1000, p
    return data, text


def test_reference(env, capsys):
    refs = reference.list_references(env["cache"])
    assert len(refs) == 1
    info = refs[0]
    assert info["scene"]["params"] == {"res": "24"}
    assert info["resolution"] == [24, 24]
    assert info["recipe"]["method"] == ("mitsuba" if HAS_MI else "mpg")
    names = {r["renderer"] for r in info["renderers"]}
    assert names == ({"mitsuba:ptracer", "mitsuba:path"} if HAS_MI else {"mpg:path"})
    for r in info["renderers"]:
        assert r["spp"] > 0 and r["seconds"] > 0
    c = info["convergence"]
    for k in ("rse_image_mean", "median_pixel_rel_error", "rse_caustic_mean",
              "relmse_floor_image", "relmse_floor_caustic", "mse_floor_image", "mse_floor_caustic"):
        assert c[k] is not None and math.isfinite(c[k]) and c[k] >= 0, k
    rgb, var = reference.load_reference(info)
    assert rgb.shape == (24, 24, 3) and var is not None and np.isfinite(var).all()
    assert c["mse_floor_image"] == pytest.approx(float(var.astype(np.float64).mean()), rel=1e-5)
    assert rgb.mean() > 0.01
    assert info["command"].startswith("mpg-bench reference ")
    # the same command finds it in the cache; --list shows it
    again = reference.make_reference(runners_scene(env), time=1, passes=4,
                                     method=info["recipe"]["method"], cache=env["cache"])
    assert again["key"] == info["key"]
    capsys.readouterr()
    assert cli.main(["reference", "--list", "--cache", env["cache"]]) == 0
    assert "tiny[res=24]" in capsys.readouterr().out


def runners_scene(env):
    from mpg.bench.scenes import resolve_scene

    return resolve_scene(env["scene"], {"res": "24"})


def test_compare(env):
    out = env["dir"] / "compare"
    assert cli.main(["compare", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     *INTEGRATORS, "--time", "0.4", "--seeds", "2", "--cache", env["cache"],
                     "--out", str(out)]) == 0
    data, text = check_out(out, ["compare-tiny_res_24_.png"])
    (sc,) = data["scenes"]
    assert [m["integrator"] for m in sc["methods"]] == INTEGRATORS
    for m in sc["methods"]:
        assert len(m["runs"]) == 2
        for region in ("image", "caustic"):
            for k in ("mse", "relmse", "mape"):
                s = m["summary"][region][k]
                assert s["n"] == 2 and s["mean"] > 0 and s["std"] >= 0
            # the render's own MSE: the measured one less the reference's floor
            floor = sc["reference"]["convergence"][f"mse_floor_{region}"]
            assert m["summary"]["mse_above_floor"][region] == pytest.approx(
                m["summary"][region]["mse"]["mean"] - floor, rel=1e-9, abs=1e-15)
            # the seeds' variance (metrics.seed_variance; tested in test_metrics)
            sv = m["summary"]["seed_variance"][region]
            assert sv is not None and sv > 0 and np.isfinite(sv)
        assert 0.2 < m["summary"]["seconds"]["mean"] < 1.0
    assert "relMSE caustic" in text and "MSE − floor caustic" in text and "seed var. caustic" in text


def test_compare_interleaves_the_methods(env, monkeypatch):
    """Seeds outer, methods inner, the order rotated by one per seed, so a drift
    of the machine's speed falls on every method alike; results keep the
    methods' order, and a method that fails is skipped without stopping the others."""
    from mpg.bench import compare
    from mpg.errors import RenderError

    calls = []
    real = compare.run_timed

    def spy(spec, sc, times, seed, threads=None):
        calls.append((seed, spec.text))
        if spec.text == "sms":
            raise RenderError("refused for the test")
        return real(spec, sc, times, seed=seed, threads=threads)

    monkeypatch.setattr(compare, "run_timed", spy)
    out = env["dir"] / "compare_order"
    assert cli.main(["compare", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     "path", "sms", "sms_star", "--time", "0.1", "--seeds", "3", "--cache", env["cache"],
                     "--out", str(out)]) == 0
    assert calls == [(0, "path"), (0, "sms"), (0, "sms_star"), (1, "sms_star"), (1, "path"),
                     (2, "sms_star"), (2, "path")]
    data, _ = check_out(out, [])
    (sc,) = data["scenes"]
    assert [m["integrator"] for m in sc["methods"]] == ["path", "sms_star"]
    assert [r["seed"] for r in sc["methods"][0]["runs"]] == [0, 1, 2]
    assert sc["skipped"] == [{"integrator": "sms", "reason": "refused for the test"}]


def test_curves(env):
    out = env["dir"] / "curves"
    integ = ["path"] + (["mitsuba:ptracer"] if HAS_MI else [])
    assert cli.main(["curves", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     *integ, "--times", "0.2", "0.4", "--seeds", "2", "--cache", env["cache"],
                     "--out", str(out)]) == 0
    data, text = check_out(out, ["curves-tiny_res_24_.png"])
    (sc,) = data["scenes"]
    for m in sc["methods"]:
        assert [p["budget"] for p in m["points"]] == [0.2, 0.4]
        for p in m["points"]:
            assert p["summary"]["image"]["relmse"]["mean"] > 0
    tt = sc["time_to_target_image"]
    assert tt["target_relmse"] > 0 and tt["methods"]["path"]["seconds"] > 0
    assert "Time to relMSE" in text
    for m in sc["methods"]:   # two seeds: each budget's seed variance
        assert all(p["summary"]["seed_variance"]["image"] > 0 for p in m["points"])


def test_curves_of_the_seeds_variance(env):
    """--metric seed_var plots the seeds' variance (metrics.seed_variance):
    the path tracer's falls with the budget (four times the time, about a
    quarter of the variance: the check fails only if the 2-seed estimates
    are off by 4x between them, which the sphere's caustic tails could do
    in a few pixels but not over all 1 728 values), and one seed is refused."""
    out = env["dir"] / "curves_sv"
    assert cli.main(["curves", "--scenes", env["scene"], "--param", "res=24", "--integrators", "path",
                     "--times", "0.2", "0.8", "--seeds", "2", "--metric", "seed_var",
                     "--cache", env["cache"], "--out", str(out)]) == 0
    data, text = check_out(out, ["curves-tiny_res_24_.png"])
    (m,) = data["scenes"][0]["methods"]
    sv = [p["summary"]["seed_variance"]["image"] for p in m["points"]]
    assert 0 < sv[1] < sv[0]
    assert "seed_var @ 0.8 s" in text
    assert cli.main(["curves", "--scenes", env["scene"], "--param", "res=24", "--integrators", "path",
                     "--times", "0.2", "--seeds", "1", "--metric", "seed_var",
                     "--cache", env["cache"], "--out", str(out)]) == 1


def test_curves_interleave_the_integrators(env, capsys):
    """curves runs seed by seed, every integrator within a seed, their order
    turned by one each seed, so a drift of the machine's speed falls on all
    alike; the report keeps the order given (the first is the targets'
    reference)."""
    out = env["dir"] / "curves_order"
    assert cli.main(["curves", "--scenes", env["scene"], "--param", "res=24", "--integrators", "path", "sms_star",
                     "--times", "0.1", "--seeds", "3", "--metric", "seed_var",
                     "--cache", env["cache"], "--out", str(out)]) == 0
    order = re.findall(r"\[curves\] .* (path|sms_star) seed (\d+) budget", capsys.readouterr().err)
    assert order == [("path", "0"), ("sms_star", "0"), ("sms_star", "1"), ("path", "1"),
                     ("path", "2"), ("sms_star", "2")]
    data = json.loads((out / "results.json").read_text())
    methods = data["scenes"][0]["methods"]
    assert [m["integrator"] for m in methods] == ["path", "sms_star"]
    assert all([r["seed"] for r in p["runs"]] == [0, 1, 2] for m in methods for p in m["points"])


def test_costs(env):
    out = env["dir"] / "costs"
    assert cli.main(["costs", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     *INTEGRATORS, "--time", "0.3", "--out", str(out)]) == 0
    data, text = check_out(out, ["costs.png"])
    assert [r["integrator"] for r in data["rows"]] == INTEGRATORS
    for r in data["rows"]:
        assert r["stats"]["spp"] > 0 and r["stats"]["seconds"] > 0
    assert "–" in text     # path reports no guiding statistics


def test_costs_mpg_spp_cell(env):
    """The "training + rendering" cell: mpg's image holds its rendering
    passes alone (the cell once printed spp - spp_training as the
    rendering's, 127 + 164 for a render of 127 + 291)."""
    out = env["dir"] / "costs-mpg"
    assert cli.main(["costs", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     "mpg", "--time", "0.6", "--out", str(out)]) == 0
    data, text = check_out(out, ["costs.png"])
    (row,) = data["rows"]
    st = row["all_stats"]
    assert st["spp_training"] > 0 and st["spp"] == st["spp_rendering"] > 0
    assert f"| {report.fmt(st['spp_training'])} + {report.fmt(st['spp_rendering'])} |" in text


def test_fresh_process_script(env, tmp_path):
    """bench/fresh_process.py: one mpg-render per render, two variants
    interleaved over two seeds; per variant its runs, MSE, seeds' variance,
    spp and MSE by training spp, all finite; a variant that is not a JSON
    object is refused."""
    import os
    import pathlib
    import subprocess
    import sys
    script = pathlib.Path(__file__).resolve().parents[1] / "bench" / "fresh_process.py"
    dest = tmp_path / "fresh.json"
    run_env = dict(os.environ, MPG_CACHE=env["cache"])
    base = [sys.executable, str(script), env["scene"], "--param", "res=24", "--time", "0.3", "--seeds", "2"]
    out = subprocess.run(base + ["--variants", "{}", '{"training_continue": true}', "--out", str(dest)],
                         capture_output=True, text=True, timeout=120, env=run_env)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    assert [v["variant"] for v in d["variants"]] == [{}, {"training_continue": True}]
    for v in d["variants"]:
        finite_numbers(v)
        assert len(v["runs"]) == 2 and v["spp"] > 0 and v["seed_variance"] > 0
        assert sum(g["renders"] for g in v["mse_by_training_spp"].values()) == 2
    assert all(v["code"] == "tree" and v["seconds_between_passes"] >= 0.0 for v in d["variants"])
    assert "paired" not in d["variants"][0] and d["variants"][1]["paired"]["seeds"] == 2
    assert d["variants"][1]["paired"]["against"] == {"variant": {}, "code": "tree"}
    assert "95 % interval" in out.stdout
    bad = subprocess.run(base + ["--variants", "[1]"], capture_output=True, text=True, timeout=60, env=run_env)
    assert bad.returncode == 2 and "JSON object" in bad.stderr


def test_fresh_process_baseline(env, tmp_path):
    """fresh_process.py --baseline REV: each variant also with REV's
    python/mpg (here HEAD's), interleaved, labelled by its code; a REV whose
    cpp/ differs from the tree's is refused. Skipped outside a git checkout
    or where the tree's cpp/ differs from HEAD's (a core being edited)."""
    import os
    import pathlib
    import subprocess
    import sys
    root = pathlib.Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or subprocess.run(
            ["git", "-C", str(root), "diff", "--quiet", "HEAD", "--", "cpp", "CMakeLists.txt"]).returncode != 0:
        pytest.skip("not a git checkout, or its cpp/ differs from HEAD's")
    dest = tmp_path / "fresh.json"
    run_env = dict(os.environ, MPG_CACHE=env["cache"])
    base = [sys.executable, str(root / "bench" / "fresh_process.py"), env["scene"], "--param", "res=24",
            "--time", "0.3", "--seeds", "2"]
    out = subprocess.run(base + ["--baseline", "HEAD", "--out", str(dest)],
                         capture_output=True, text=True, timeout=120, env=run_env)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    assert [(v["variant"], v["code"]) for v in d["variants"]] == [({}, "tree"), ({}, "HEAD")]
    assert d["variants"][1]["paired"]["against"] == {"variant": {}, "code": "tree"}
    for v in d["variants"]:
        assert len(v["runs"]) == 2 and v["spp"] > 0 and v["seed_variance"] > 0
    assert "[HEAD]" in out.stdout and "[tree]" in out.stdout
    # (the first commit with a core: its cpp/ differs from today's)
    first = subprocess.run(["git", "-C", str(root), "rev-list", "--max-parents=0", "HEAD"],
                           capture_output=True, text=True).stdout.split()[0]
    bad = subprocess.run(base + ["--baseline", first], capture_output=True, text=True, timeout=60, env=run_env)
    assert bad.returncode == 1 and "differs from the working tree" in bad.stderr


def test_fresh_process_paired_ratio():
    """fresh_process.paired_ratio: the ratio of the two means on the seeds
    both rendered, an interval around it that holds it, a degenerate
    interval where every seed's ratio is the same, and NaN (not an error)
    with fewer than two common seeds."""
    paired_ratio = bench_module("fresh_process").paired_ratio
    rng = np.random.default_rng(3)
    m = rng.lognormal(0.0, 1.0, 40)
    first = [{"seed": i, "mse": float(2.0 * v)} for i, v in enumerate(m)]
    other = [{"seed": i, "mse": float(v)} for i, v in enumerate(m)] + [{"seed": 99, "mse": 5.0}]
    r = paired_ratio(first, other)
    assert r["seeds"] == 40 and r["ratio"] == pytest.approx(2.0)
    assert r["ci95"] == pytest.approx([2.0, 2.0])
    noisy = [{"seed": i, "mse": float(v * rng.lognormal(0.0, 0.5))} for i, v in enumerate(m)]
    r = paired_ratio(first, noisy)
    assert r["ci95"][0] < r["ratio"] < r["ci95"][1]
    assert paired_ratio(first, noisy) == r   # (a fixed generator)
    assert np.isnan(paired_ratio(first[:1], other[:1])["ratio"])


def test_missing_mitsuba_is_skipped(env, monkeypatch):
    monkeypatch.setattr(runners, "mitsuba_importable", lambda: False)
    out = env["dir"] / "nomi"
    assert cli.main(["compare", "--scenes", env["scene"], "--param", "res=24", "--integrators",
                     "path", "mitsuba:path", "--time", "0.2", "--seeds", "1", "--cache",
                     env["cache"], "--out", str(out)]) == 0
    data, text = check_out(out, [])
    (sc,) = data["scenes"]
    assert [m["integrator"] for m in sc["methods"]] == ["path"]
    assert sc["skipped"][0]["integrator"] == "mitsuba:path"
    assert "mitsuba is not installed" in text


def test_bad_inputs(env, capsys):
    assert cli.main(["compare", "--scenes", "no_such_scene"]) == 1
    assert "not found" in capsys.readouterr().err
    assert cli.main(["compare", "--scenes", env["scene"], "--integrators", "foo:bar"]) == 1
    assert cli.main(["compare", "--scenes", env["scene"], "--param", "res=24", "--integrators", "path", "path",
                     "--cache", env["cache"]]) == 1
    assert "given twice" in capsys.readouterr().err
    assert cli.main(["reference", env["scene"]]) == 1


def test_time_to_target():
    t = [1.0, 2.0, 4.0, 8.0]
    e = [0.8, 0.4, 0.2, 0.1]
    r = curves.time_to_target(t, e, 0.3)
    assert r["seconds"] == pytest.approx(2.0 * 2 ** (math.log(0.3 / 0.4) / math.log(0.5)))
    assert not r["extrapolated"]
    r = curves.time_to_target(t, e, 0.05)          # below the range: 1/t from the last point
    assert r["seconds"] == pytest.approx(16.0) and r["extrapolated"]
    flat = curves.time_to_target(t, [0.5, 0.49, 0.48, 0.47], 0.1)
    assert flat["seconds"] is None and flat["not_reached"]


def test_reference_combination_rule():
    h = w = 12
    path = np.full((h, w, 3), 1.0)
    pt = np.full((h, w, 3), 1.0)
    path_var = np.full((h, w, 3), 0.5)
    pt_var = np.full((h, w, 3), 0.1)
    eligible = np.ones((h, w), bool)
    eligible[:, :3] = False                         # "glass seen by the camera"
    pt[:, :3] = 0.0
    pt_var[:, :3] = 0.0                             # black with zero variance there
    pt_var[6, 6] = 2.0             # above path's 0.5, but its own variance does not decide
    rgb, var, chose = reference.combine(path, path_var, pt, pt_var, eligible)
    assert not chose[:, :3].any() and (rgb[:, :3] == 1.0).all()
    assert chose[:, 3:].all()
    assert chose[6, 6] and var[6, 6, 0] == 2.0
    # path wins where its neighbourhood variance is lower
    rgb, var, chose = reference.combine(path, np.full((h, w, 3), 0.01), pt, pt_var, eligible)
    assert not chose.any()


def test_reference_hint_from_sidecar():
    assert reference.parse_hint("mitsuba path: purely diffuse") == ("mitsuba", ["path"])
    assert reference.parse_hint("mitsuba ptracer+path: small light") == (
        "mitsuba", ["ptracer", "path"])
    assert reference.parse_hint("mitsuba ptracer: point light") == ("mitsuba", ["ptracer"])
    assert reference.parse_hint("mpg long run (sms_star)") == ("mpg", None)
    assert reference.parse_hint("") == (None, None)


def test_reference_camera_delta(env, tmp_path):
    """--camera-delta: the reference is the sum of two renders, `--integrator`
    without and the named integrator with only the light seen from the camera
    through delta scattering; image and variance are exactly those renders'
    sums, the recipe and command name it, and a recipe without it keeps the
    key of older references (no 'camera_delta' entry)."""
    import mpg

    sc = runners_scene(env)
    info = reference.make_reference(sc, spp=4, passes=2, method="mpg", integrator="sms_star",
                                    camera_delta="path", cache=str(tmp_path))
    assert [r["renderer"] for r in info["renderers"]] == [
        "mpg:sms_star/camera_delta=exclude", "mpg:path/camera_delta=only"]
    assert "--camera-delta path" in info["command"]
    assert info["recipe"]["camera_delta"] == "path"
    s = mpg.load_file(env["scene"], res=24)
    seed = reference.DEFAULT_SEED
    a = mpg.render(s, {"type": "sms_star", "camera_delta": "exclude"}, spp=4, seed=seed, progress=False)
    b = mpg.render(s, {"type": "path", "camera_delta": "only"}, spp=4, seed=seed + 500_000,
                   progress=False)
    rgb, var = reference.load_reference(info)
    np.testing.assert_allclose(rgb, a.rgb.astype(np.float64) + b.rgb, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(var, a.variance.astype(np.float64) + b.variance, rtol=1e-5, atol=1e-9)
    plain = reference.recipe(sc, time=1, spp=None, passes=4, seed=seed, method="mpg", integrator="path")
    assert "camera_delta" not in plain
    if HAS_MI:
        with pytest.raises(BenchError, match="needs --method mpg"):
            reference.recipe(sc, time=1, spp=None, passes=4, seed=seed, method="mitsuba",
                             integrator="path", camera_delta="path")
    with pytest.raises(BenchError, match="without its own camera_delta"):
        reference.recipe(sc, time=1, spp=None, passes=4, seed=seed, method="mpg", integrator="path",
                         camera_delta="path/camera_delta=all")


@pytest.mark.skipif(not HAS_MI, reason="the fill replaces Mitsuba's path tracer: needs Mitsuba")
def test_reference_fill(env, tmp_path):
    """--fill: Mitsuba's light tracer wherever it sees the pixel; the pixels it
    cannot see (glass seen by the camera, dilated) come from the named mpg
    integrator rendering only their bounding box (a crop window), exactly that
    crop render's values and variances; Mitsuba's path tracer is not run. A
    sidecar reference_fill is used by default, and then a cached Mitsuba
    reference without the fill is not chosen, however low its noise floor."""
    import dataclasses

    import mpg
    from mpg.bench.scenes import resolve_scene

    sc = runners_scene(env)
    info = reference.make_reference(sc, spp=4, passes=2, fill="sms_star", cache=str(tmp_path))
    assert info["recipe"]["fill"] == "sms_star" and "--fill sms_star" in info["command"]
    assert [r["renderer"] for r in info["renderers"]] == ["mitsuba:ptracer", "mpg:sms_star"]
    x0, y0, w, h = info["renderers"][1]["crop"]
    assert 0 < w * h < 24 * 24
    rgb, var = reference.load_reference(info)
    s = mpg.load_file(env["scene"], res=24)
    cam = s.desc.camera
    sub = mpg.render(mpg.Scene(desc=dataclasses.replace(s.desc, camera=dataclasses.replace(
        cam, crop=(cam.crop[0] + x0, cam.crop[1] + y0, w, h)))), "sms_star", spp=4,
        seed=reference.DEFAULT_SEED + 250_000, progress=False)
    win = rgb[y0:y0 + h, x0:x0 + w]
    filled = np.all(win == sub.rgb, axis=2)
    n_fill = round((1.0 - info["ptracer_fraction"]) * 24 * 24)
    assert filled.sum() >= n_fill > 0           # (a ptracer pixel may equal by chance: black)
    np.testing.assert_array_equal(var[y0:y0 + h, x0:x0 + w][filled], sub.variance[filled])
    # the sidecar's reference_fill is the default, and decides which cached reference is used:
    # the same scene file beside a sidecar that asks for the fill (same content hash)
    side = json.loads((env["dir"] / "tiny.json").read_text())
    (tmp_path / "f").mkdir()
    shutil.copy(env["scene"], tmp_path / "f" / "tiny.xml")
    (tmp_path / "f" / "tiny.json").write_text(json.dumps(dict(side, reference_fill="sms_star")))
    fsc = resolve_scene(str(tmp_path / "f" / "tiny.xml"), {"res": "24"})
    assert fsc.content_hash() == sc.content_hash()
    assert reference.recipe(fsc, time=1, spp=None, passes=2, seed=1, method="auto",
                            integrator="path")["fill"] == "sms_star"
    assert "fill" not in reference.recipe(sc, time=1, spp=None, passes=2, seed=1, method="auto",
                                          integrator="path")
    # env's cache holds a Mitsuba ptracer+path reference of this scene: found without the
    # sidecar's fill, passed over with it; the fill reference is found either way
    assert reference.find_reference(sc, env["cache"]) is not None
    assert reference.find_reference(fsc, env["cache"]) is None
    assert reference.find_reference(fsc, str(tmp_path))["key"] == info["key"]
    with pytest.raises(BenchError, match="must be an mpg integrator"):
        reference.recipe(sc, time=1, spp=None, passes=2, seed=1, method="mitsuba",
                         integrator="path", fill="mitsuba:path")
    with pytest.raises(BenchError, match="needs a Mitsuba reference"):
        reference.recipe(sc, time=1, spp=None, passes=2, seed=1, method="mpg",
                         integrator="path", fill="sms_star")


def test_pass_overhead_script(tmp_path):
    """bench/pass_overhead.py: the same spp as 1-spp passes and as longer
    ones, per thread count; positive, finite times, their ratio and the
    overhead a pass written to the JSON; an --spp that --long does not divide
    is refused."""
    import pathlib
    import subprocess
    import sys
    script = pathlib.Path(__file__).resolve().parents[1] / "bench" / "pass_overhead.py"
    dest = tmp_path / "po.json"
    base = [sys.executable, str(script), "--scene", "sphere", "--spp", "4", "--long", "2", "--repeats", "1"]
    out = subprocess.run(base + ["--threads", "1", "2", "--out", str(dest)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    finite_numbers(d)
    assert set(d["threads"]) == {"1", "2"}
    for row in d["threads"].values():
        assert row["short_seconds"] > 0 and row["long_seconds"] > 0
        assert row["ratio"] == pytest.approx(row["short_seconds"] / row["long_seconds"])
        assert row["overhead_ms_per_pass"] == pytest.approx(1000 * (row["short_seconds"] - row["long_seconds"]) / 4)
    bad = subprocess.run(base[:4] + ["--spp", "5", "--long", "2"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "multiple" in bad.stderr
