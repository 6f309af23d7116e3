"""`mpg-bench compare`: equal-time renders against the reference, K seeds each.

For every scene and integrator entry, K renders (seeds 0..K-1) with the same wall
time; MSE / relMSE / MAPE against the reference over the whole image and the
caustic box; mean ± sample standard deviation over the seeds. One side-by-side
PNG per scene (seed 0's images, the caustic box enlarged under each).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from mpg import metrics
from mpg.bench import reference as refmod
from mpg.bench import report
from mpg.bench.runners import BenchError, IntegratorSpec, RunResult, log, run_timed
from mpg.bench.scenes import BenchScene
from mpg.errors import MPGError

METRIC_NAMES = ("mse", "relmse", "mape")
REGIONS = ("image", "caustic")


def error_record(r: RunResult, ref: np.ndarray, box) -> dict[str, Any]:
    m = metrics.all_metrics(r.rgb, ref, box)
    return {"seconds": r.seconds, "spp": r.spp, "metrics": m}


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and spread over seeds of every metric, seconds and spp."""
    out: dict[str, Any] = {"seconds": report.spread([r["seconds"] for r in runs]),
                           "spp": report.spread([r["spp"] for r in runs])}
    for reg in REGIONS:
        if runs[0]["metrics"][reg] is None:
            out[reg] = None
            continue
        out[reg] = {k: report.spread([r["metrics"][reg][k] for r in runs]) for k in METRIC_NAMES}
    return out


def above_floor(summ: dict[str, Any], conv: dict[str, Any]) -> dict[str, Any]:
    """Mean MSE over the seeds minus the reference's MSE floor, per region.

    The reference is unbiased and independent of the render, so in expectation
    MSE(render, reference) = MSE(render, truth) + floor, with floor the mean
    variance of the reference's pixels (reference.convergence). The difference
    is an unbiased estimate of the render's own MSE; it can come out negative
    when the render's error is below the reference's noise, and is then
    reported as it is (a sign the reference is too noisy to rank the render)."""
    out: dict[str, Any] = {}
    for reg in REGIONS:
        fl = conv.get(f"mse_floor_{reg}")
        if summ.get(reg) is None or fl is None or summ[reg]["mse"]["mean"] is None:
            out[reg] = None
        else:
            out[reg] = float(summ[reg]["mse"]["mean"] - fl)
    return out


def seed_variances(images: list[np.ndarray], box) -> dict[str, Any] | None:
    """Per region the seeds' sample variance (metrics.seed_variance): one
    render's MSE for an unbiased integrator, free of the reference's noise.
    None with fewer than 2 seeds."""
    if len(images) < 2:
        return None
    return {"image": metrics.seed_variance(images),
            "caustic": metrics.seed_variance(images, box) if box is not None else None}


def skip_reason(spec: IntegratorSpec) -> str | None:
    from mpg.bench.runners import mitsuba_importable

    if spec.backend == "mitsuba" and not mitsuba_importable():
        return "mitsuba is not installed"
    return None


def run(scenes: list[BenchScene], specs: list[IntegratorSpec], time: float, seeds: int,
        out: str, argv, cache: str | None, reference_time: float | None,
        threads: int | None = None, exposure: float = 0.0) -> dict[str, Any]:
    if not time > 0:
        raise BenchError(f"--time must be positive, got {time}")
    if seeds < 1:
        raise BenchError(f"--seeds must be at least 1, got {seeds}")
    dup = sorted({s.text for s in specs if sum(t.text == s.text for t in specs) > 1})
    if dup:   # the runs are kept per entry
        raise BenchError(f"integrator entries given twice: {', '.join(dup)}")
    results: dict[str, Any] = {"command": report.command_line(argv), "time": time,
                               "seeds": seeds, "scenes": []}
    md = [report.header("Equal-time comparison", argv),
          (f"Budget {time:g} s per render, {seeds} seed(s) per method, the methods run in "
           "turn per seed (order rotated by one per seed); errors are mean ± "
           "sample standard deviation over the seeds (one seed: no spread). Metrics: "
           "docs/results.md.\n")]
    for sc in scenes:
        ref_info = refmod.get_or_make(sc, cache, reference_time or max(10.0, 20.0 * time))
        ref, ref_var = refmod.load_reference(ref_info)
        box = sc.caustic_box
        srec: dict[str, Any] = {"scene": sc.to_json(),
                                "reference": _ref_summary(ref_info, ref, ref_var, box),
                                "methods": [], "skipped": []}
        shown: list[tuple[str, np.ndarray, str]] = []
        active = []
        for spec in specs:
            why = skip_reason(spec)
            if why:
                log(f"mpg-bench: skipping {spec.text}: {why}")
                srec["skipped"].append({"integrator": spec.text, "reason": why})
            else:
                active.append(spec)
        # Seeds outer, methods inner in an order rotated by one per seed (A B C,
        # B C A, ...): a drift of the machine's speed during the run (up to 1.3x
        # between runs here) falls on every method alike.
        runs: dict[str, list[dict[str, Any]]] = {spec.text: [] for spec in active}
        images: dict[str, list[np.ndarray]] = {spec.text: [] for spec in active}
        firsts: dict[str, Any] = {}
        failed: dict[str, str] = {}
        for s in range(seeds):
            k = s % len(active) if active else 0
            for spec in active[k:] + active[:k]:
                if spec.text in failed:
                    continue
                try:
                    (r,) = run_timed(spec, sc, [time], seed=s, threads=threads)
                    if r.rgb.shape != ref.shape:
                        raise BenchError(f"{spec.text}: image {r.rgb.shape} but reference "
                                         f"{ref.shape}")
                except MPGError as e:
                    log(f"mpg-bench: skipping {spec.text} on {sc.label}: {e}")
                    failed[spec.text] = str(e)
                    continue
                rec = error_record(r, ref, box)
                rec.update(seed=s, stats=r.stats)
                runs[spec.text].append(rec)
                images[spec.text].append(r.rgb)
                log(f"[compare] {sc.label} {spec.text} seed {s}: {r.seconds:.2f} s, "
                    f"{r.spp} spp, relMSE {rec['metrics']['image']['relmse']:.4g}")
                if s == 0:
                    firsts[spec.text] = r
        for spec in active:
            if spec.text in failed:
                srec["skipped"].append({"integrator": spec.text, "reason": failed[spec.text]})
                continue
            summ = summarise(runs[spec.text])
            summ["mse_above_floor"] = above_floor(summ, srec["reference"]["convergence"])
            summ["seed_variance"] = seed_variances(images[spec.text], box)
            srec["methods"].append({"integrator": spec.text, "runs": runs[spec.text], "summary": summ})
            m0 = runs[spec.text][0]["metrics"]
            label = f"relMSE {report.fmt(m0['image']['relmse'])}"
            if m0["caustic"] is not None:
                label += f"\ncaustic {report.fmt(m0['caustic']['relmse'])}"
            shown.append((spec.text, firsts[spec.text].rgb, label))
        png = f"compare-{_safe(sc.label)}.png"
        report.side_by_side(os.path.join(out, png), f"{sc.label}: equal time {time:g} s",
                            ref, shown, box, exposure)
        srec["figure"] = png
        results["scenes"].append(srec)
        md.append(_scene_md(sc, srec, png))
    report.write_json(os.path.join(out, "results.json"), results)
    report.write_text(os.path.join(out, "report.md"), "\n".join(md))
    return results


def _safe(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in s)


def _ref_summary(info: dict[str, Any], rgb: np.ndarray, var: np.ndarray | None,
                 box) -> dict[str, Any]:
    """The reference's record; convergence recomputed for this scene's caustic box (the
    cache is keyed by content, so a sidecar box added later still gets its numbers)."""
    out = {k: info.get(k) for k in ("exr", "key", "recipe", "renderers", "combination",
                                    "ptracer_fraction", "convergence", "command")}
    if var is not None:
        out["convergence"] = refmod.convergence(rgb, var, box)
    return out


def _scene_md(sc: BenchScene, srec: dict[str, Any], png: str) -> str:
    c = srec["reference"]["convergence"]
    lines = [f"## {sc.label}\n"]
    if sc.sidecar.get("description"):
        lines.append(str(sc.sidecar["description"]) + "\n")
    lines.append(f"Reference: `{srec['reference']['command']}` — median pixel relative error "
                 f"{report.fmt(c['median_pixel_rel_error'])}, relMSE floor (its own noise) "
                 f"{report.fmt(c['relmse_floor_image'])} image / "
                 f"{report.fmt(c['relmse_floor_caustic'])} caustic, MSE floor "
                 f"{report.fmt(c.get('mse_floor_image'))} image / "
                 f"{report.fmt(c.get('mse_floor_caustic'))} caustic.\n")
    has_box = sc.caustic_box is not None
    header = ["integrator", "time (s)", "spp (mean)", "MSE", "relMSE", "MAPE",
              "MSE − floor", "seed var."]
    if has_box:
        header += ["MSE caustic", "relMSE caustic", "MAPE caustic", "MSE − floor caustic",
                   "seed var. caustic"]
    rows = []
    for m in srec["methods"]:
        s = m["summary"]
        row = [m["integrator"], report.fmt_spread(s["seconds"]),
               report.fmt(round(s["spp"]["mean"]))]
        af = s.get("mse_above_floor") or {}
        sv = s.get("seed_variance") or {}
        row += [report.fmt_spread(s["image"][k]) for k in METRIC_NAMES]
        row += [report.fmt(af.get("image")), report.fmt(sv.get("image"))]
        if has_box:
            row += [report.fmt_spread(s["caustic"][k]) for k in METRIC_NAMES]
            row += [report.fmt(af.get("caustic")), report.fmt(sv.get("caustic"))]
        rows.append(row)
    lines.append(report.md_table(header, rows))
    lines.append("\n\"MSE − floor\": the mean MSE less the reference's MSE floor, an unbiased "
                 "estimate of the render's own MSE (negative: below the reference's noise). "
                 "\"seed var.\": the seeds' sample variance per pixel, averaged (metrics.seed_variance; "
                 "two or more seeds): one render's MSE if the integrator is unbiased, with no "
                 "reference noise in it.")
    for sk in srec["skipped"]:
        lines.append(f"\n*{sk['integrator']} skipped: {sk['reason']}*")
    lines.append(f"\n![{sc.label}]({png})\n")
    return "\n".join(lines)
