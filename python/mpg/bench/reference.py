"""Reference images with their estimated per-pixel error, cached outside git.

How a reference is made (`mpg-bench reference SCENE --time S | --spp N`):

- Mitsuba 3 (the default when it is installed and the sidecar's "reference"
  text does not say 'mpg'): its light tracer `ptracer` (converges floor caustics
  fast) and its path tracer `path` (the only one of the two that sees through
  glass and mirrors), each as >= K passes with distinct seeds; per pixel the
  variance of the mean is the sample variance over passes / passes. The budget
  is split evenly between the two. The sidecar's "reference" text can narrow
  this: 'mitsuba path: ...' renders path only; 'mitsuba ptracer: ...' takes
  ptracer wherever it sees the pixel (path would be biased there, e.g. a point
  light seen through glass) and path only for the pixels ptracer cannot see.
  With `--fill INTEGRATOR` (or the sidecar's "reference_fill") those pixels
  are rendered by that mpg integrator instead of Mitsuba's path tracer, over
  their bounding box only, with half the budget: a point light's caustic seen
  through glass (L-TT-D-TT-E on sphere_point) is reached by neither Mitsuba
  renderer, but by a chain integrator such as sms_star.
- mpg (`--method mpg`, or the sidecar says 'mpg'): one long mpg.render of
  `--integrator` (default path); its variance is the per-pixel second-moment
  estimate of the render loop.
  With `--camera-delta INTEGRATOR` (e.g. path) the light that reaches the
  camera through delta scattering only (a light seen in ideal glass or a
  mirror) is rendered apart: `--integrator` with camera_delta=exclude and
  INTEGRATOR with camera_delta=only, half the budget each, added (variances
  add: the two renders are independent). Both integrators estimate that light
  the same way, one camera path at a time, but the "only" render stops at the
  first non-delta vertex and so takes 50-100x the samples: a tiny bright light
  whose image through bumpy glass is a few glints per image then stops
  dominating the reference's own noise (emitter_size_001: the MSE floor of
  a 180 s sms_star reference was 1.83, 99.97 % of it one glint pixel).

Combination rule (Mitsuba): per pixel, take the whole RGB estimate of the
renderer with the lower variance. Two details make this unbiased:

1. ptracer is only eligible where it estimates the pixel at all: pixels where a
   primary ray (3x3 stratified per pixel, dilated by one pixel) hits a surface
   with a delta BSDF lobe or misses the scene get `path` (ptracer renders glass
   seen by the camera black, with zero variance — "lower variance" would pick it).
2. The variances compared are not the pixel's own estimates but their mean over
   the 5x5 neighbourhood *without the pixel itself*. A pixel's own mean and
   variance estimates are correlated (a pass set that missed the rare bright
   paths has both a low mean and a low variance), so choosing by its own
   variance would favour low estimates: a downward bias. With box filtering the
   neighbours' passes are independent of the pixel's (up to ptracer light
   paths that splat into several pixels), so the choice does not depend on the
   pixel's own values and each pixel keeps an unbiased estimate.

Inverse-variance weighting is not used: with variances estimated from a few
passes the weights correlate with the estimates (same bias as above), and
ptracer's zero-variance black pixels would get infinite weight.

The variance is compared in luminance with the channels taken as fully
correlated, (sum_c w_c sigma_c)^2, which is how a renderer's channels behave (one
path carries all three).

Cache: DIR/<scene name>-<key>.{exr,json,png}; DIR is --cache, else $MPG_CACHE,
else ~/.cache/mpg/references. The key hashes the scene file, the files it names
(meshes, textures, includes), its parameters, and how the reference was made,
so the same command finds (or re-creates) the same file.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import shlex
from typing import Any

import numpy as np

from mpg.bench.runners import (
    IntegratorSpec,
    log,
    mitsuba_importable,
    parse_integrator,
    run_mitsuba,
    run_mpg,
    scene_rfilter,
)
from mpg.bench.scenes import BenchError, BenchScene
from mpg.metrics import EPS, region_mask

LUM = np.array([0.2126, 0.7152, 0.0722])
DEFAULT_SEED = 1_000_000   # far from the seeds the compared renders use (0 .. K-1)
NEIGHBOURHOOD = 2          # radius of the window whose variances decide a pixel


def cache_dir(arg: str | None = None) -> str:
    return os.path.abspath(os.path.expanduser(
        arg or os.environ.get("MPG_CACHE") or "~/.cache/mpg/references"))


def lum_variance(var: np.ndarray) -> np.ndarray:
    """Luminance variance of a pixel with fully correlated channels."""
    return (np.sqrt(np.maximum(var, 0.0)) @ LUM) ** 2


def neighbourhood_mean(v: np.ndarray, valid: np.ndarray, r: int = NEIGHBOURHOOD) -> np.ndarray:
    """Mean of v over the valid pixels of the (2r+1)^2 window, excluding the centre
    (inf where the window has no valid pixel)."""
    h, w = v.shape
    vm = np.where(valid, v, 0.0)
    pv = np.pad(vm, r)
    pm = np.pad(valid.astype(np.float64), r)
    s = np.zeros((h, w))
    c = np.zeros((h, w))
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            if dy == r and dx == r:
                continue
            s += pv[dy:dy + h, dx:dx + w]
            c += pm[dy:dy + h, dx:dx + w]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c > 0, s / np.maximum(c, 1), np.inf)


def dilate(mask: np.ndarray, r: int = 1) -> np.ndarray:
    h, w = mask.shape
    p = np.pad(mask, r)
    out = np.zeros_like(mask)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out |= p[dy:dy + h, dx:dx + w]
    return out


def combine(path_rgb, path_var, pt_rgb, pt_var, pt_eligible) -> tuple[np.ndarray, np.ndarray,
                                                                       np.ndarray]:
    """Per-pixel choice by lower neighbourhood variance (see the module doc).
    Returns (rgb, variance, chose_ptracer mask)."""
    lp = lum_variance(path_var)
    lt = lum_variance(pt_var)
    full = np.ones(lp.shape, dtype=bool)
    choose = pt_eligible & (neighbourhood_mean(lt, pt_eligible) < neighbourhood_mean(lp, full))
    rgb = np.where(choose[:, :, None], pt_rgb, path_rgb)
    var = np.where(choose[:, :, None], pt_var, path_var)
    return rgb.astype(np.float32), var.astype(np.float32), choose


def convergence(rgb: np.ndarray, var: np.ndarray, box) -> dict[str, Any]:
    """Relative standard error of the image mean and of the caustic-box mean (pixels
    independent), median per-pixel relative error (luminance), and the relMSE and
    MSE the reference's own noise adds to every comparison (mean var / (ref^2 +
    eps), mean var): in expectation a measured MSE is the true one plus this floor,
    so an error far below it cannot be measured against this reference."""
    rgb = np.asarray(rgb, np.float64)
    var = np.asarray(var, np.float64)

    def rse(m):
        x, v = rgb[m], var[m]
        mean = x.mean()
        return float(np.sqrt(v.sum()) / x.size / mean) if mean > 0 else None

    lum = rgb @ LUM
    pix_rel = np.sqrt(lum_variance(var)) / (np.abs(lum) + EPS)
    floor = var / (rgb * rgb + EPS)
    out = {
        "rse_image_mean": rse(np.ones(rgb.shape[:2], bool)),
        "median_pixel_rel_error": float(np.median(pix_rel)),
        "relmse_floor_image": float(floor.mean()),
        "mse_floor_image": float(var.mean()),
        "rse_caustic_mean": None,
        "median_pixel_rel_error_caustic": None,
        "relmse_floor_caustic": None,
        "mse_floor_caustic": None,
    }
    if box is not None:
        m = region_mask(rgb.shape[:2], box)
        out["rse_caustic_mean"] = rse(m)
        out["median_pixel_rel_error_caustic"] = float(np.median(pix_rel[m]))
        out["relmse_floor_caustic"] = float(floor[m].mean())
        out["mse_floor_caustic"] = float(var[m].mean())
    return out


def parse_hint(text: str) -> tuple[str | None, list[str] | None]:
    """The sidecar's "reference" text: 'mpg ...' -> ('mpg', None); 'mitsuba path: ...',
    'mitsuba ptracer+path: ...', 'mitsuba ptracer: ...' -> ('mitsuba', the integrators)."""
    m = re.match(r"\s*(mitsuba|mpg)\b\s*([a-z_]+(?:\s*\+\s*[a-z_]+)*)?", text.lower())
    if not m:
        return None, None
    if m.group(1) == "mpg":
        return "mpg", None
    names = [n.strip() for n in (m.group(2) or "").split("+") if n.strip()]
    names = [n for n in names if n in ("path", "ptracer")]
    return "mitsuba", names or None


def choose_method(scene: BenchScene, method: str) -> tuple[str, list[str] | None]:
    """(method, Mitsuba integrators): --method, else the sidecar hint, else Mitsuba
    ptracer+path when installed, else mpg."""
    if method not in ("auto", "mitsuba", "mpg"):
        raise BenchError(f"--method must be auto, mitsuba or mpg, got '{method}'")
    hint_method, hint_names = parse_hint(scene.reference_hint)
    m = method if method != "auto" else (hint_method or "mitsuba")
    if m == "mitsuba" and not mitsuba_importable():
        if method == "mitsuba":
            raise BenchError("--method mitsuba: mitsuba is not installed")
        log(f"mpg-bench: mitsuba is not installed; the reference of {scene.label} is an mpg "
            "render")
        m = "mpg"
    if m == "mpg":
        return "mpg", None
    names = hint_names or ["ptracer", "path"]
    if "ptracer" in names and "path" not in names:
        names = names + ["path"]    # path fills the pixels the light tracer cannot see
    return "mitsuba", sorted(set(names), key=["ptracer", "path"].index)


def recipe(scene: BenchScene, *, time: float | None, spp: int | None, passes: int, seed: int,
           method: str, integrator: str, camera_delta: str | None = None,
           fill: str | None = None) -> dict[str, Any]:
    if (time is None) == (spp is None):
        raise BenchError("give exactly one of --time and --spp for a reference")
    if time is not None and not time > 0:
        raise BenchError(f"--time must be positive, got {time}")
    if spp is not None and spp < 1:
        raise BenchError(f"--spp must be at least 1, got {spp}")
    if passes < 2:
        raise BenchError(f"--passes must be at least 2 (variance from passes), got {passes}")
    m, names = choose_method(scene, method)
    rec = {"method": m, "mitsuba_integrators": names, "time": None if time is None else float(time),
           "spp": None if spp is None else int(spp), "passes": int(passes), "seed": int(seed),
           "integrator": integrator if m == "mpg" else None}
    if camera_delta is not None:   # (absent otherwise: the keys of older references stay valid)
        if m != "mpg":
            raise BenchError("--camera-delta needs --method mpg")
        for name in (integrator, camera_delta):
            spec = parse_integrator(name)
            if spec.backend != "mpg" or any(k == "camera_delta" for k, _ in spec.params):
                raise BenchError(f"--camera-delta: '{name}' must be an mpg integrator without "
                                 "its own camera_delta")
        rec["camera_delta"] = camera_delta
    if fill is None and m == "mitsuba":
        fill = scene.reference_fill
    if fill is not None:           # (absent otherwise, as camera_delta)
        if m != "mitsuba" or "ptracer" not in (names or []):
            raise BenchError("--fill needs a Mitsuba reference with its light tracer "
                             f"(got method {m}, integrators {names})")
        if parse_integrator(fill).backend != "mpg":
            raise BenchError(f"--fill: '{fill}' must be an mpg integrator")
        rec["fill"] = fill
    return rec


def key_of(scene_hash: str, rec: dict[str, Any]) -> str:
    return hashlib.sha256((scene_hash + json.dumps(rec, sort_keys=True)).encode()).hexdigest()


def recreate_command(scene: BenchScene, rec: dict[str, Any]) -> str:
    parts = ["mpg-bench", "reference", scene.path]
    parts += ["--time", f"{rec['time']:g}"] if rec["time"] is not None else ["--spp",
                                                                             str(rec["spp"])]
    parts += ["--passes", str(rec["passes"]), "--seed", str(rec["seed"]),
              "--method", rec["method"]]
    if rec["method"] == "mpg":
        parts += ["--integrator", rec["integrator"]]
    if rec.get("camera_delta"):
        parts += ["--camera-delta", rec["camera_delta"]]
    if rec.get("fill"):
        parts += ["--fill", rec["fill"]]
    for k, v in sorted(scene.params.items()):
        parts += ["--param", f"{k}={v}"]
    return " ".join(shlex.quote(p) for p in parts)


def make_reference(scene: BenchScene, *, time: float | None = None, spp: int | None = None,
                   passes: int = 8, seed: int = DEFAULT_SEED, method: str = "auto",
                   integrator: str = "path", cache: str | None = None,
                   force: bool = False, camera_delta: str | None = None,
                   fill: str | None = None) -> dict[str, Any]:
    """Render (or find in the cache) a reference; returns its JSON record (with 'exr')."""
    rec = recipe(scene, time=time, spp=spp, passes=passes, seed=seed, method=method,
                 integrator=integrator, camera_delta=camera_delta, fill=fill)
    scene_hash = scene.content_hash()
    key = key_of(scene_hash, rec)
    d = cache_dir(cache)
    stem = os.path.join(d, f"{scene.name}-{key[:16]}")
    if not force and os.path.isfile(stem + ".json") and os.path.isfile(stem + ".exr"):
        with open(stem + ".json") as f:
            info = json.load(f)
        log(f"mpg-bench: reference of {scene.label} is cached: {stem}.exr")
        return info
    log(f"mpg-bench: rendering the reference of {scene.label} ({rec['method']}, "
        + (f"{time:g} s" if time is not None else f"{spp} spp") + f", {passes} passes)")
    renderers: list[dict[str, Any]] = []
    notes: list[str] = []
    if rec["method"] == "mpg":
        spec = parse_integrator(integrator)
        if spec.backend != "mpg":
            raise BenchError(f"--integrator for an mpg reference must be an mpg integrator, "
                             f"got '{integrator}'")
        ptracer_fraction = 0.0
        if not rec.get("camera_delta"):
            r = run_mpg(spec, scene, time=time, spp=spp, seed=seed)
            rgb, var = r.rgb, r.variance
            renderers.append({"renderer": f"mpg:{integrator}", "spp": r.spp, "seconds": r.seconds,
                              "passes": r.stats.get("passes"), "seed": seed})
            combination = "single mpg render (variance from its per-pixel second moment)"
        else:
            rgb = var = None
            half = None if time is None else time / 2
            for text, mode, sd in ((integrator, "exclude", seed), (rec["camera_delta"], "only",
                                                                  seed + 500_000)):
                sp = parse_integrator(f"{text}/camera_delta={mode}")
                r = run_mpg(sp, scene, time=half, spp=spp, seed=sd)
                if r.variance is None:
                    raise BenchError(f"reference of {scene.label}: {sp.text} gave no variance")
                rgb = r.rgb.astype(np.float64) if rgb is None else rgb + r.rgb
                var = r.variance.astype(np.float64) if var is None else var + r.variance
                renderers.append({"renderer": f"mpg:{sp.text}", "spp": r.spp, "seconds": r.seconds,
                                  "passes": r.stats.get("passes"), "seed": sd})
                log(f"  {sp.text}: {r.spp} spp, {r.seconds:.1f} s")
            rgb, var = rgb.astype(np.float32), var.astype(np.float32)
            combination = (f"sum of {integrator} without and {rec['camera_delta']} with only the light "
                           "seen from the camera through delta scattering (variances added)")
    else:
        rgb, var, ptracer_fraction, combination = _mitsuba_reference(
            scene, rec, renderers, notes)
    if not (np.isfinite(rgb).all() and np.isfinite(var).all()):
        raise BenchError(f"reference of {scene.label}: non-finite pixels; not cached")
    from mpg.image import write_exr, write_png

    os.makedirs(d, exist_ok=True)
    write_exr(stem + ".exr", rgb, var)
    write_png(stem + ".png", rgb)
    info = {
        "scene": scene.to_json(), "scene_hash": scene_hash, "key": key,
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
        "recipe": rec, "renderers": renderers, "combination": combination,
        "ptracer_fraction": ptracer_fraction, "notes": notes,
        "resolution": [int(rgb.shape[1]), int(rgb.shape[0])],
        "convergence": convergence(rgb, var, scene.caustic_box),
        "exr": stem + ".exr", "png": stem + ".png",
        "command": recreate_command(scene, rec), "versions": _versions(),
    }
    with open(stem + ".json", "w") as f:
        json.dump(info, f, indent=2)
    c = info["convergence"]
    log(f"mpg-bench: wrote {stem}.exr (median pixel rel. error {c['median_pixel_rel_error']:.3g},"
        f" image-mean rel. SE {_fmt(c['rse_image_mean'])})")
    return info


def _fmt(x) -> str:
    return "–" if x is None else f"{x:.3g}"


def _versions() -> dict[str, str]:
    import mpg

    out = {"mpg": mpg.__version__}
    try:
        from importlib.metadata import version

        out["mitsuba"] = version("mitsuba")
    except Exception:
        pass
    return out


def _mitsuba_reference(scene: BenchScene, rec: dict, renderers: list, notes: list):
    passes = rec["passes"]
    names = rec["mitsuba_integrators"]
    want_pt = "ptracer" in names
    # the sidecar named ptracer alone: path only fills the pixels ptracer cannot see
    pt_only = want_pt and scene.reference_hint and "path" not in (parse_hint(
        scene.reference_hint)[1] or ["path"])
    fill = rec.get("fill")
    if fill and scene_rfilter(scene) != "box":
        raise BenchError(f"reference of {scene.label}: --fill needs the light tracer, which needs "
                         f"a box rfilter (the scene's is '{scene_rfilter(scene)}')")
    if want_pt and scene_rfilter(scene) != "box":
        want_pt = False
        notes.append(f"ptracer not used: the scene's rfilter is '{scene_rfilter(scene)}' "
                     "(light-tracer splats then correlate neighbouring pixels)")
    n_renderers = 2 if want_pt else 1
    results = {}
    mask = None
    for name in (["ptracer"] if want_pt else []) + ([] if fill else ["path"]):
        spec = IntegratorSpec(f"mitsuba:{name}", "mitsuba", name)
        seed = rec["seed"] + (0 if name == "path" else 500_000)
        try:
            if rec["time"] is not None:
                t = rec["time"] / n_renderers
                res, m = run_mitsuba(spec, scene, seed=seed, checkpoints=[t],
                                     target_pass_seconds=0.8 * t / passes, mask=name == "ptracer")
            else:
                res, m = run_mitsuba(spec, scene, seed=seed, spp=rec["spp"], passes=passes,
                                     mask=name == "ptracer")
        except BenchError as e:
            if name == "ptracer" and not fill:
                notes.append(f"ptracer failed, path only: {e}")
                log(f"mpg-bench: {e}; the reference uses path only")
                continue
            raise
        r = res[0]
        if r.variance is None:
            raise BenchError(f"reference of {scene.label}: {spec.text} finished only one pass; "
                             "give a larger budget")
        if m is not None:
            mask = m
        results[name] = r
        renderers.append({"renderer": spec.text, "variant": r.stats["variant"], "spp": r.spp,
                          "passes": r.stats["passes"], "pass_spp": r.stats["pass_spp"],
                          "seconds": r.seconds, "seed": seed,
                          "integrator_params": r.stats["integrator_params"]})
        log(f"  {spec.text} ({r.stats['variant']}): {r.spp} spp in {r.stats['passes']} passes, "
            f"{r.seconds:.1f} s")
    if "ptracer" not in results:
        p = results["path"]
        return (p.rgb, p.variance, 0.0,
                "Mitsuba path only (variance from passes)")
    t = results["ptracer"]
    eligible = ~dilate(mask.astype(bool), 1)
    if fill:
        return _fill_reference(scene, rec, t, eligible, renderers, notes)
    p = results["path"]
    if pt_only:
        chose = eligible
        rgb = np.where(chose[:, :, None], t.rgb, p.rgb).astype(np.float32)
        var = np.where(chose[:, :, None], t.variance, p.variance).astype(np.float32)
        notes.append("the sidecar names ptracer only: ptracer wherever it can see the pixel, "
                     "path elsewhere (paths neither reaches, e.g. a point light seen through "
                     "glass from a surface seen through glass, are missing there)")
        return (rgb, var, float(chose.mean()),
                "ptracer where eligible (sidecar), path for the pixels it cannot see")
    rgb, var, chose = combine(p.rgb, p.variance, t.rgb, t.variance, eligible)
    return (rgb, var, float(chose.mean()),
            ("per pixel, the renderer (ptracer or path) with the lower luminance variance over "
             f"the {2 * NEIGHBOURHOOD + 1}x{2 * NEIGHBOURHOOD + 1} neighbourhood excluding the "
             "pixel; ptracer only where no primary ray hits a delta BSDF or misses "
             "(dilated 1 px)"))


def _fill_reference(scene: BenchScene, rec: dict, t, eligible: np.ndarray, renderers: list, notes: list):
    """ptracer's image wherever it sees the pixel; the rest (primary rays that
    hit a delta BSDF or miss, dilated by one pixel) from rec["fill"], an mpg
    integrator rendering only the bounding box of those pixels (a crop window
    of the camera) with the other half of the budget. Each pixel keeps one
    renderer's unbiased estimate and its variance; the choice is by geometry."""
    import dataclasses

    from mpg.render import Scene

    rgb = t.rgb.astype(np.float32).copy()
    var = t.variance.astype(np.float32).copy()
    todo = ~eligible
    if todo.any():
        ys, xs = np.nonzero(todo)
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        loaded = scene.load_mpg()
        cam = loaded.desc.camera
        crop = (cam.crop[0] + x0, cam.crop[1] + y0, x1 - x0, y1 - y0)
        sub = Scene(desc=dataclasses.replace(loaded.desc, camera=dataclasses.replace(cam,
                                                                                        crop=crop)))
        spec = parse_integrator(rec["fill"])
        seed = rec["seed"] + 250_000
        r = run_mpg(spec, scene, time=None if rec["time"] is None else rec["time"] / 2,
                    spp=rec["spp"], seed=seed, loaded=sub)
        if r.variance is None:
            raise BenchError(f"reference of {scene.label}: {spec.text} gave no variance")
        win = todo[y0:y1, x0:x1, None]
        rgb[y0:y1, x0:x1] = np.where(win, r.rgb, rgb[y0:y1, x0:x1])
        var[y0:y1, x0:x1] = np.where(win, r.variance, var[y0:y1, x0:x1])
        renderers.append({"renderer": f"mpg:{spec.text}", "spp": r.spp, "seconds": r.seconds,
                          "passes": r.stats.get("passes"), "seed": seed,
                          "crop": [x0, y0, x1 - x0, y1 - y0]})
        log(f"  mpg:{spec.text} on the {x1 - x0}x{y1 - y0} window ptracer cannot see: "
            f"{r.spp} spp, {r.seconds:.1f} s")
    notes.append(f"ptracer wherever it can see the pixel, mpg {rec['fill']} for the "
                 f"{int(todo.sum())} pixels it cannot see (no Mitsuba path)")
    return (rgb, var, float(eligible.mean()),
            f"ptracer where eligible, mpg {rec['fill']} for the pixels it cannot see")


def list_references(cache: str | None = None) -> list[dict[str, Any]]:
    d = cache_dir(cache)
    out = []
    if not os.path.isdir(d):
        return out
    for fn in sorted(os.listdir(d)):
        if fn.endswith(".json"):
            try:
                with open(os.path.join(d, fn)) as f:
                    info = json.load(f)
            except (OSError, ValueError):
                continue
            if isinstance(info, dict) and "scene_hash" in info and os.path.isfile(
                    info.get("exr", "")):
                out.append(info)
    return out


def find_reference(scene: BenchScene, cache: str | None = None) -> dict[str, Any] | None:
    """The cached reference of this scene content + params with the lowest noise floor."""
    h = scene.content_hash()
    cands = [i for i in list_references(cache) if i["scene_hash"] == h]
    if scene.reference_fill:
        # the sidecar says which light only a chain integrator reaches: a Mitsuba
        # reference without that fill misses it, however low its noise floor
        cands = [i for i in cands if i.get("recipe", {}).get("method") != "mitsuba"
                 or i.get("recipe", {}).get("fill")]
    if not cands:
        return None
    return min(cands, key=lambda i: i["convergence"]["relmse_floor_image"])


def load_reference(info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray | None]:
    from mpg.image import read_exr

    return read_exr(info["exr"])


def get_or_make(scene: BenchScene, cache: str | None, time: float,
                passes: int = 8) -> dict[str, Any]:
    info = find_reference(scene, cache)
    if info is not None:
        return info
    log(f"mpg-bench: no cached reference for {scene.label}; making one ({time:g} s). "
        f"For a better one: mpg-bench reference {scene.path} --time SECONDS")
    return make_reference(scene, time=time, passes=passes, cache=cache)
