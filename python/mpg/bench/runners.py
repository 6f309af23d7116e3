"""Integrator entries: an mpg integrator by name, or Mitsuba 3 as `mitsuba:NAME[@VARIANT]`.

    path                        mpg's path tracer (any name mpg.render accepts)
    mitsuba:path                Mitsuba 3's path tracer, llvm_ad_rgb if it works, else scalar_rgb
    mitsuba:ptracer@scalar_rgb  Mitsuba 3's light tracer in the scalar variant

mpg entries render in this process through mpg.render(time=...). Mitsuba entries
render in a child process (mpg.bench.mitsuba_worker) as passes of a fixed spp
until the time is up; its kernel-compile warm-up is not counted (see there).
Both use the integrator parameters of the scene file (max_depth, rr_depth,
hide_emitters), so the two renderers solve the same equation.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time as _time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpg.bench.scenes import BenchError, BenchScene

MITSUBA_VARIANTS = ("llvm_ad_rgb", "scalar_rgb")
_variant_ok: dict[str, bool] = {}      # variant -> it rendered (or crashed) in a child


@dataclass(frozen=True)
class IntegratorSpec:
    text: str
    backend: str          # 'mpg' | 'mitsuba'
    name: str
    variant: str | None = None
    params: tuple[tuple[str, str], ...] = ()   # mpg entries: NAME/key=value/key=value

    @property
    def label(self) -> str:
        return self.text


def parse_integrator(text: str) -> IntegratorSpec:
    t = text.strip()
    if not t:
        raise BenchError("empty integrator name")
    if t.startswith("mitsuba:"):
        rest = t[len("mitsuba:"):]
        name, _, variant = rest.partition("@")
        if not name:
            raise BenchError(f"'{t}': expected mitsuba:NAME[@VARIANT], e.g. mitsuba:path")
        return IntegratorSpec(t, "mitsuba", name, variant or None)
    if ":" in t or "@" in t:
        raise BenchError(f"'{t}': unknown backend (mpg integrators by name, or mitsuba:NAME)")
    name, *kvs = t.split("/")
    params = []
    for kv in kvs:
        k, eq, v = kv.partition("=")
        if not k or not eq:
            raise BenchError(f"'{t}': expected NAME/key=value/..., e.g. mpg/init=photon")
        params.append((k, v))
    from mpg.errors import RenderError
    from mpg.render import check_param_names
    try:   # a typo is caught before any render of the run (`sampler` is the render's: run_mpg)
        check_param_names(name, [k for k, _ in params if k != "sampler"])
    except RenderError as e:
        raise BenchError(f"'{t}': {e}") from None
    return IntegratorSpec(t, "mpg", name, None, tuple(params))


def mitsuba_importable() -> bool:
    try:
        import importlib.util

        return importlib.util.find_spec("mitsuba") is not None
    except (ImportError, ValueError):
        return False


@dataclass
class RunResult:
    rgb: np.ndarray                    # (H, W, 3) float32 mean
    variance: np.ndarray | None        # variance of the mean, or None
    seconds: float                     # wall time counted against the budget
    spp: int
    stats: dict[str, Any] = field(default_factory=dict)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------- mpg

_scene_cache: dict[tuple, Any] = {}


def _mpg_scene(scene: BenchScene):
    key = (scene.path, tuple(sorted(scene.params.items())))
    if key not in _scene_cache:
        _scene_cache.clear()            # keep one built scene at a time
        _scene_cache[key] = scene.load_mpg()
    return _scene_cache[key]


def run_mpg(spec: IntegratorSpec, scene: BenchScene, *, time: float | None = None,
            spp: int | None = None, seed: int = 0, threads: int | None = None,
            loaded=None) -> RunResult:
    """One mpg render of the bench scene, or of `loaded` (an mpg.Scene made from
    it, e.g. with a crop window) when given."""
    import mpg

    s = loaded if loaded is not None else _mpg_scene(scene)
    _ = s.core                          # build the BVH before the clock (as mpg.render does)
    integ: Any = spec.name
    # `sampler` in an entry (path/sampler=stratified) is the render's, not the
    # integrator's.
    params = dict(spec.params)
    sampler = params.pop("sampler", None)
    if params:
        integ = dict(params, type=spec.name)
    img = mpg.render(s, integrator=integ, spp=spp, time=time, seed=seed, threads=threads,
                     progress=False, sampler=sampler)
    if img.spp == 0:
        raise BenchError(f"{spec.text} on {scene.label}: no pass finished within {time} s")
    st = dict(img.stats)
    return RunResult(img.rgb, img.variance, float(st.get("seconds", 0.0)), img.spp, st)


# ---------------------------------------------------------------- Mitsuba


def scene_integrator_params(scene: BenchScene) -> dict[str, Any]:
    """max_depth / rr_depth / hide_emitters of the scene's <integrator>, for Mitsuba's."""
    desc = _mpg_scene(scene).desc
    out: dict[str, Any] = {}
    for k in ("max_depth", "rr_depth"):
        if k in desc.integrator.params:
            out[k] = int(desc.integrator.params[k])
    if "hide_emitters" in desc.integrator.params:
        out["hide_emitters"] = bool(desc.integrator.params["hide_emitters"])
    return out


def scene_rfilter(scene: BenchScene) -> str:
    return _mpg_scene(scene).desc.camera.rfilter.type


def _child(job: dict, timeout: float | None) -> tuple[dict, dict] | str:
    """Run the worker; its result, or an error text."""
    with tempfile.TemporaryDirectory(prefix="mpg-bench-") as tmp:
        job = dict(job, out=os.path.join(tmp, "out"))
        jp = os.path.join(tmp, "job.json")
        with open(jp, "w") as f:
            json.dump(job, f)
        try:
            p = subprocess.run([sys.executable, "-m", "mpg.bench.mitsuba_worker", jp],
                               capture_output=True, text=True, check=False,
                               timeout=timeout)
        except subprocess.TimeoutExpired:
            return f"timed out after {timeout:.0f} s"
        if p.returncode != 0 or not os.path.isfile(job["out"] + ".json"):
            tail = (p.stderr or "").strip().splitlines()[-3:]
            return f"exit code {p.returncode}: " + " | ".join(tail)
        with np.load(job["out"] + ".npz") as z:
            arrays = {k: z[k] for k in z.files}
        with open(job["out"] + ".json") as f:
            info = json.load(f)
    return arrays, info


def run_mitsuba(spec: IntegratorSpec, scene: BenchScene, *, seed: int = 0,
                checkpoints: list[float] | None = None, spp: int | None = None,
                passes: int | None = None, pass_spp: int | None = None, mask: bool = False,
                target_pass_seconds: float | None = None) -> tuple[list[RunResult], Any]:
    """Time mode (checkpoints: one result per checkpoint) or spp mode (spp in `passes`
    passes). Returns (results, mask or None). Raises BenchError if Mitsuba cannot render."""
    if not mitsuba_importable():
        raise BenchError("mitsuba is not installed (pip install mitsuba, or the 'bench' extra)")
    job: dict[str, Any] = {
        "scene": scene.path, "params": scene.params, "integrator": spec.name,
        "integrator_params": scene_integrator_params(scene), "seed": int(seed), "mask": mask,
        "progress": False,
    }
    if checkpoints:
        job.update(mode="time", checkpoints=list(checkpoints), pass_spp=pass_spp,
                   target_pass_seconds=target_pass_seconds)
        timeout = 3.0 * max(checkpoints) + 300.0
    else:
        if not spp or not passes:
            raise BenchError("run_mitsuba: give checkpoints (time) or spp and passes")
        job.update(mode="spp", pass_spp=max(1, spp // passes), passes=passes)
        timeout = None
    variants = [spec.variant] if spec.variant else [
        v for v in MITSUBA_VARIANTS if _variant_ok.get(v, True)]
    errors = []
    for v in variants:
        t0 = _time.perf_counter()
        out = _child(dict(job, variant=v), timeout)
        if isinstance(out, str):
            errors.append(f"{v}: {out}")
            if not spec.variant:
                _variant_ok[v] = False
                log(f"mpg-bench: Mitsuba {v} failed ({out}); trying the next variant")
            continue
        _variant_ok[v] = True
        arrays, info = out
        results = []
        for i, snap in enumerate(info["snapshots"]):
            var = arrays[f"var_{i}"]
            results.append(RunResult(
                rgb=arrays[f"mean_{i}"], variance=var if np.isfinite(var).all() else None,
                seconds=float(snap["seconds"]), spp=int(snap["spp"]),
                stats={"integrator": spec.text, "variant": info["variant"],
                       "spp": int(snap["spp"]), "passes": int(snap["passes"]),
                       "pass_spp": int(snap["pass_spp"]), "seconds": float(snap["seconds"]),
                       "warmup_seconds": float(info.get("warmup_seconds", 0.0)),
                       "process_seconds": _time.perf_counter() - t0, "seed": int(seed),
                       "integrator_params": job["integrator_params"]}))
        return results, arrays.get("mask")
    raise BenchError(f"{spec.text} on {scene.label}: Mitsuba could not render: "
                     + "; ".join(errors))


# ---------------------------------------------------------------- any entry


def run_timed(spec: IntegratorSpec, scene: BenchScene, times: list[float], seed: int,
              threads: int | None = None) -> list[RunResult]:
    """One result per time budget. mpg: a separate render per budget (an integrator's
    training schedule may depend on its budget). Mitsuba: one progressive run with
    snapshots at the budgets."""
    if spec.backend == "mitsuba":
        res, _ = run_mitsuba(spec, scene, seed=seed, checkpoints=list(times))
        return res
    return [run_mpg(spec, scene, time=t, seed=seed, threads=threads) for t in times]
