"""`mpg-bench curves`: error against wall time (log-log), like MPG Fig. 11.

For each scene, integrator entry and seed, the image at each time budget
(mpg: a separate render per budget, since an integrator's training schedule may
depend on the budget; Mitsuba: one progressive run with snapshots). Error = the
chosen metric (default relMSE) over the image and the caustic box; the curve is
the mean over seeds and the band ± one sample standard deviation (as the paper
shades it), clipped at a small positive value for the log axis.

Time to reach a target relMSE: on the mean curve, linear interpolation in
(log t, log relMSE) between the two budgets that bracket the target. Outside the
measured range it is extrapolated with Monte Carlo's error ~ 1/t from the nearest
point and marked as extrapolated — but only if the curve still falls (log-log slope
of its last two points steeper than -0.5); a curve that has flattened (a biased
method, e.g. ptracer on pixels it cannot reach) is "not reached". The default
target is, per scene and region, the final mean relMSE of the first integrator
listed (the baseline), so the table reads as "time to the baseline's quality at
the longest budget" and the speed-up column as speed-up over the baseline.
"""

from __future__ import annotations

import itertools
import math
import os
from typing import Any

import numpy as np

from mpg.bench import reference as refmod
from mpg.bench import report
from mpg.bench.compare import METRIC_NAMES, _ref_summary, _safe, error_record, skip_reason
from mpg.bench.runners import BenchError, IntegratorSpec, log, run_timed
from mpg.bench.scenes import BenchScene
from mpg.errors import MPGError

# --metric seed_var: the seeds' sample variance at each budget
# (metrics.seed_variance), an unbiased method's MSE with no reference noise in
# it, so the long budgets are not flattened by the reference's floor
SEED_VAR = "seed_var"


def time_to_target(seconds: list[float], errors: list[float], target: float) -> dict[str, Any]:
    """Time at which a (decreasing) error curve reaches `target`, log-log interpolated."""
    pts = [(t, e) for t, e in zip(seconds, errors) if t and e and t > 0 and e > 0]
    if not pts or not target > 0:
        return {"seconds": None, "extrapolated": False}
    pts.sort()
    for (t0, e0), (t1, e1) in itertools.pairwise(pts):
        if (e0 - target) * (e1 - target) <= 0 and e0 != e1:
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return {"seconds": math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0))),
                    "extrapolated": False}
    if pts[0][1] < target:                   # reached before the first budget
        t, e = pts[0]
        return {"seconds": t * e / target, "extrapolated": True}
    if len(pts) >= 2:                         # not reached: extrapolate only if converging
        (t0, e0), (t1, e1) = pts[-2], pts[-1]
        slope = (math.log(e1) - math.log(e0)) / (math.log(t1) - math.log(t0)) if t1 > t0 else 0
        if slope > -0.5:
            return {"seconds": None, "extrapolated": False, "not_reached": True}
    t, e = pts[-1]
    return {"seconds": t * e / target, "extrapolated": True}


def run(scenes: list[BenchScene], specs: list[IntegratorSpec], times: list[float], seeds: int,
        out: str, argv, cache: str | None, reference_time: float | None,
        target_relmse: float | None = None, metric: str = "relmse",
        threads: int | None = None) -> dict[str, Any]:
    times = sorted(float(t) for t in times)
    if not times or not all(t > 0 for t in times):
        raise BenchError(f"--times must be positive, got {times}")
    if seeds < 1:
        raise BenchError(f"--seeds must be at least 1, got {seeds}")
    if metric not in METRIC_NAMES + (SEED_VAR,):
        raise BenchError(f"--metric must be one of {', '.join(METRIC_NAMES + (SEED_VAR,))}")
    if metric == SEED_VAR and seeds < 2:
        raise BenchError(f"--metric {SEED_VAR} needs --seeds 2 or more (it is the seeds' variance)")
    results: dict[str, Any] = {"command": report.command_line(argv), "times": times,
                               "seeds": seeds, "metric": metric, "scenes": []}
    md = [report.header("Error against time", argv),
          (f"Budgets {', '.join(f'{t:g}' for t in times)} s, {seeds} seed(s), the integrators run in "
           "turn per seed (order rotated by one per seed); curves are the "
           "mean over seeds, bands ± one sample standard deviation. Time to target: log-log "
           "interpolation on the mean relMSE curve (`*`: extrapolated with error ~ 1/t); the "
           "default target is the first integrator's final relMSE."
           + (" seed_var: the seeds' variance at each budget, one number, no band."
              if metric == SEED_VAR else "") + "\n")]
    for sc in scenes:
        ref_info = refmod.get_or_make(sc, cache, reference_time or max(10.0, 20.0 * times[-1]))
        ref, ref_var = refmod.load_reference(ref_info)
        box = sc.caustic_box
        srec: dict[str, Any] = {"scene": sc.to_json(),
                                "reference": _ref_summary(ref_info, ref, ref_var, box),
                                "methods": [], "skipped": []}
        active = []
        for spec in specs:
            why = skip_reason(spec)
            if why:
                log(f"mpg-bench: skipping {spec.text}: {why}")
                srec["skipped"].append({"integrator": spec.text, "reason": why})
            else:
                active.append(spec)
        per_time = [[[] for _ in times] for _ in active]
        images = [[[] for _ in times] for _ in active]
        failed: dict[int, str] = {}
        # Seeds outer, integrators inner, their order turned by one each
        # seed: a drift of the machine's speed during the run falls on every
        # integrator alike (run one after another, double_slabs' `path` ran
        # 34 spp/s where it had run 40 an hour before, while `mpg` kept its
        # pace: its ratio read 1.17x too high; docs/results.md, forty-fifth
        # session).
        for s in range(seeds):
            for j in range(len(active)):
                a = (s + j) % len(active)
                spec = active[a]
                if a in failed:
                    continue
                try:
                    for i, r in enumerate(run_timed(spec, sc, times, seed=s, threads=threads)):
                        rec = error_record(r, ref, box)
                        rec.update(seed=s, budget=times[i])
                        per_time[a][i].append(rec)
                        images[a][i].append(r.rgb)
                        log(f"[curves] {sc.label} {spec.text} seed {s} budget {times[i]:g} s: "
                            f"{r.seconds:.2f} s, {r.spp} spp, "
                            f"relMSE {rec['metrics']['image']['relmse']:.4g}")
                except MPGError as e:
                    log(f"mpg-bench: skipping {spec.text} on {sc.label}: {e}")
                    failed[a] = str(e)
        from mpg.bench.compare import seed_variances, summarise

        for a, spec in enumerate(active):   # (in the order given: the first is the targets' reference)
            if a in failed:
                srec["skipped"].append({"integrator": spec.text, "reason": failed[a]})
                continue
            points = [{"budget": t, "runs": runs, "summary": dict(summarise(runs), seed_variance=seed_variances(ims, box))}
                      for t, runs, ims in zip(times, per_time[a], images[a])]
            srec["methods"].append({"integrator": spec.text, "points": points})
        _targets(srec, target_relmse)
        png = f"curves-{_safe(sc.label)}.png"
        _plot(os.path.join(out, png), sc, srec, metric)
        srec["figure"] = png
        results["scenes"].append(srec)
        md.append(_scene_md(sc, srec, png, metric))
    report.write_json(os.path.join(out, "results.json"), results)
    report.write_text(os.path.join(out, "report.md"), "\n".join(md))
    return results


def _curve(m: dict[str, Any], region: str, metric: str):
    t = [p["summary"]["seconds"]["mean"] for p in m["points"]]
    if m["points"][0]["summary"][region] is None:
        return None
    if metric == SEED_VAR:   # one number per budget: no band
        mean = [p["summary"]["seed_variance"][region] for p in m["points"]]
        return t, mean, [0.0] * len(mean)
    mean = [p["summary"][region][metric]["mean"] for p in m["points"]]
    std = [p["summary"][region][metric]["std"] for p in m["points"]]
    return t, mean, std


def _targets(srec: dict[str, Any], target: float | None) -> None:
    for region in ("image", "caustic"):
        curves = {m["integrator"]: _curve(m, region, "relmse") for m in srec["methods"]}
        curves = {k: v for k, v in curves.items() if v is not None}
        if not curves:
            srec[f"time_to_target_{region}"] = None
            continue
        tgt = target if target else next(iter(curves.values()))[1][-1]
        res = {k: time_to_target(c[0], c[1], tgt) for k, c in curves.items()}
        srec[f"time_to_target_{region}"] = {"target_relmse": tgt, "methods": res}


def _plot(path: str, sc: BenchScene, srec: dict[str, Any], metric: str) -> None:
    p = report.plt()
    from matplotlib.ticker import NullFormatter
    regions = ["image"] + (["caustic"] if sc.caustic_box is not None else [])
    fig, axes = p.subplots(1, len(regions), figsize=(5.0 * len(regions), 4.0), squeeze=False)
    for ax, region in zip(axes[0], regions):
        for m in srec["methods"]:
            c = _curve(m, region, metric)
            if c is None:
                continue
            t, mean, std = (np.asarray(v, dtype=np.float64) for v in c)
            line, = ax.loglog(t, mean, marker="o", ms=3, label=m["integrator"])
            lo = np.maximum(mean - std, mean * 1e-3)
            ax.fill_between(t, lo, mean + std, color=line.get_color(), alpha=0.2, lw=0)
        tt = srec.get(f"time_to_target_{region}")
        if tt and metric == "relmse":
            ax.axhline(tt["target_relmse"], color="grey", lw=0.8, ls="--")
        # the budgets as the x ticks (a log axis over one or two decades
        # otherwise labels its minor ticks on top of each other)
        budgets = [p["budget"] for p in srec["methods"][0]["points"]] if srec["methods"] else []
        if budgets:
            ax.set_xticks(budgets)
            ax.set_xticklabels([f"{b:g}" for b in budgets])
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time (s)")
        ax.set_ylabel(f"{metric} ({region})")
        ax.set_title(f"{sc.label}: {region}", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    p.close(fig)


def _cell(point: dict[str, Any], region: str, metric: str) -> str:
    if metric == SEED_VAR:
        return report.fmt((point["summary"].get("seed_variance") or {}).get(region))
    return report.fmt_spread(point["summary"][region][metric])


def _scene_md(sc: BenchScene, srec: dict[str, Any], png: str, metric: str) -> str:
    lines = [f"## {sc.label}\n", f"![{sc.label}]({png})\n"]
    has_box = sc.caustic_box is not None
    budgets = [p["budget"] for p in srec["methods"][0]["points"]] if srec["methods"] else []
    header = ["integrator"] + [f"{metric} @ {b:g} s" for b in budgets]
    rows = []
    for m in srec["methods"]:
        rows.append([m["integrator"]] + [_cell(p, "image", metric) for p in m["points"]])
    lines.append("Whole image:\n")
    lines.append(report.md_table(header, rows))
    if has_box:
        rows = [[m["integrator"]] + [_cell(p, "caustic", metric) for p in m["points"]]
                for m in srec["methods"]]
        lines.append("\nCaustic box:\n")
        lines.append(report.md_table(header, rows))
    for region in ("image", "caustic"):
        tt = srec.get(f"time_to_target_{region}")
        if not tt:
            continue
        first = None
        rows = []
        for name, r in tt["methods"].items():
            s = r["seconds"]
            first = first if first is not None else s
            star = "*" if r["extrapolated"] else ""
            speed = report.fmt(first / s) if (s and first) else report.DASH
            cell = (report.fmt(s) + star) if s else ("not reached" if r.get("not_reached")
                                                     else report.DASH)
            rows.append([name, cell, speed])
        lines.append(f"\nTime to relMSE {report.fmt(tt['target_relmse'])} ({region}):\n")
        lines.append(report.md_table(["integrator", "seconds", "speed-up vs first"], rows))
    for sk in srec["skipped"]:
        lines.append(f"\n*{sk['integrator']} skipped: {sk['reason']}*")
    return "\n".join(lines) + "\n"
