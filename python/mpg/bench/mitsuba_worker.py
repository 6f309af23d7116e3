"""Mitsuba 3 renders for mpg-bench, run in a child process:

    python -m mpg.bench.mitsuba_worker JOB.json

so that a crash (an LLVM abort), a long kernel compile or a leak cannot stop the
suite. JOB.json (written by runners.run_mitsuba) says what to render; the result
is OUT.npz (mean_<i>, var_<i> per checkpoint, optional `mask`) and OUT.json
(seconds, spp, passes per checkpoint; variant; warm-up seconds).

Passes: every pass renders `pass_spp` samples per pixel with its own seed, and
the estimate is the mean over passes; the variance of that mean is the sample
variance over passes / passes (per pixel and channel), so it is right whatever
the per-sample distribution. All passes of a run have the same spp (Mitsuba's
ptracer recompiles its kernel when spp changes).

Time mode (equal-time runs): before the clock starts, one warm-up pass at 1 spp
(compiles the kernels; the LLVM kernel cache makes later runs cheaper) and one
timed 1-spp pass pick pass_spp so that a pass takes about `target_pass_seconds`;
if pass_spp differs from 1 a second warm-up pass at pass_spp compiles that kernel.
None of this counts. Then passes run until the next one would end past the
budget (at least one pass): a snapshot is taken at each checkpoint, so one run
gives the image at 1, 2, 4, 8 s. Each snapshot's `seconds` is the wall time of
the passes it contains.
"""

from __future__ import annotations

import json
import sys
import time


def _seed(seed: int, index: int) -> int:
    return (int(seed) * 1_000_003 + int(index)) % (2 ** 32)


def delta_or_miss_mask(mi, scene, k: int = 3):
    """(H, W) bool: some of k*k stratified primary rays of the pixel miss the scene or hit a
    surface whose BSDF has a delta lobe (glass, mirror): there the light tracer cannot
    connect to the camera, so it is not an estimate of the pixel."""
    import numpy as np

    sensor = scene.sensors()[0]
    film = sensor.film()
    w, h = (int(v) for v in film.crop_size())
    n = k * k
    if mi.variant().startswith("scalar"):
        out = np.zeros((h, w), dtype=bool)
        for y in range(h):
            for x in range(w):
                for j in range(n):
                    ox, oy = ((j % k) + 0.5) / k, ((j // k) + 0.5) / k
                    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + ox) / w, (y + oy) / h),
                                               mi.Point2f(0.5))
                    si = scene.ray_intersect(ray)
                    if not si.is_valid() or mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Delta):
                        out[y, x] = True
                        break
        return out
    import drjit as dr

    idx = dr.arange(mi.UInt32, w * h * n)
    pix = idx // n
    j = idx % n
    x = mi.Float(pix % w)
    y = mi.Float(pix // w)
    ox = (mi.Float(j % k) + 0.5) / k
    oy = (mi.Float(j // k) + 0.5) / k
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5),
                               mi.Point2f((x + ox) / w, (y + oy) / h), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bad = ~si.is_valid() | mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Delta)
    return np.array(bad, dtype=bool).reshape(h, w, n).any(axis=2)


def load_scene(mi, path: str, params: dict):
    """mi.load_file, but with unused properties (the SMS/MPG shape hints that Mitsuba's
    plugins do not read) logged instead of raised, when this Mitsuba has mi.parser (3.6+)."""
    import os

    params = {k: str(v) for k, v in params.items()}
    if not hasattr(mi, "parser"):
        return mi.load_file(path, **params)
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else \
        mi.Thread.thread().file_resolver()
    folder = os.path.dirname(os.path.abspath(path))
    if folder not in [str(p) for p in fr]:
        fr.prepend(folder)
    cfg = mi.parser.ParserConfig(mi.variant())
    cfg.unused_properties = mi.LogLevel.Debug
    state = mi.parser.parse_file(cfg, path, **params)
    mi.parser.transform_upgrade(cfg, state)
    mi.parser.transform_resolve(cfg, state)
    return mi.parser.instantiate(cfg, state)


def run(job: dict) -> tuple[dict, dict]:
    import mitsuba as mi
    import numpy as np

    mi.set_variant(job["variant"])
    scene = load_scene(mi, job["scene"], job["params"])
    integ = mi.load_dict({"type": job["integrator"], **job["integrator_params"]})
    seed = int(job["seed"])
    arrays: dict = {}
    info: dict = {"variant": mi.variant(), "integrator": job["integrator"], "snapshots": []}
    if job.get("mask"):
        arrays["mask"] = delta_or_miss_mask(mi, scene)

    def render(spp: int, s: int):
        return np.array(mi.render(scene, spp=spp, seed=s, integrator=integ),
                        dtype=np.float64)[:, :, :3]

    acc = acc2 = None
    n_passes = 0

    def add(img):
        nonlocal acc, acc2, n_passes
        if acc is None:
            acc = np.zeros_like(img)
            acc2 = np.zeros_like(img)
        acc += img
        acc2 += img * img
        n_passes += 1

    def snapshot(seconds: float, pass_spp: int):
        i = len(info["snapshots"])
        mean = acc / n_passes
        if n_passes > 1:
            var = np.maximum(acc2 / n_passes - mean * mean, 0.0) / (n_passes - 1)
        else:
            var = np.full_like(mean, np.inf)
        arrays[f"mean_{i}"] = mean.astype(np.float32)
        arrays[f"var_{i}"] = var.astype(np.float32)
        info["snapshots"].append({"seconds": seconds, "spp": n_passes * pass_spp,
                                  "passes": n_passes, "pass_spp": pass_spp})

    if job["mode"] == "spp":
        pass_spp, passes = int(job["pass_spp"]), int(job["passes"])
        t0 = time.perf_counter()
        for p in range(passes):
            add(render(pass_spp, _seed(seed, p)))
            _progress(job, p + 1, passes, time.perf_counter() - t0)
        snapshot(time.perf_counter() - t0, pass_spp)
        info["warmup_seconds"] = 0.0
        return arrays, info

    checkpoints = sorted(float(c) for c in job["checkpoints"])
    tw = time.perf_counter()
    render(1, 2 ** 32 - 1)                     # compile
    t1 = time.perf_counter()
    render(1, 2 ** 32 - 2)                     # measure
    per_spp = max(time.perf_counter() - t1, 1e-6)
    target = float(job.get("target_pass_seconds") or min(checkpoints[0] / 8.0, 1.0))
    pass_spp = int(job.get("pass_spp") or max(1, min(4096, int(target / per_spp))))
    if pass_spp != 1:
        t2 = time.perf_counter()
        render(pass_spp, 2 ** 32 - 3)          # compile for this spp (ptracer)
        pass_est = time.perf_counter() - t2
    else:
        pass_est = per_spp
    info["warmup_seconds"] = time.perf_counter() - tw
    t0 = time.perf_counter()
    durations: list[float] = []
    ci = 0
    while ci < len(checkpoints):
        elapsed = time.perf_counter() - t0
        est = max(durations[-3:]) if durations else pass_est
        if n_passes > 0 and elapsed + est > checkpoints[ci]:
            snapshot(elapsed, pass_spp)
            ci += 1
            continue
        ts = time.perf_counter()
        add(render(pass_spp, _seed(seed, n_passes)))
        durations.append(time.perf_counter() - ts)
        _progress(job, time.perf_counter() - t0, checkpoints[-1], time.perf_counter() - t0)
    return arrays, info


def _progress(job: dict, done, total, elapsed: float) -> None:
    if job.get("progress"):
        sys.stderr.write(f"\r  mitsuba:{job['integrator']} {done:.4g}/{total:.4g} "
                         f"({elapsed:.1f} s)   ")
        sys.stderr.flush()


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    argv = sys.argv[1:] if argv is None else argv
    with open(argv[0]) as f:
        job = json.load(f)
    try:
        arrays, info = run(job)
    except ImportError as e:
        print(f"mitsuba_worker: mitsuba is not importable: {e}", file=sys.stderr)
        return 3
    except Exception as e:   # report any Mitsuba failure to the parent as text
        print(f"mitsuba_worker: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    if job.get("progress"):
        sys.stderr.write("\n")
    np.savez(job["out"] + ".npz", **arrays)
    with open(job["out"] + ".json", "w") as f:
        json.dump(info, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
