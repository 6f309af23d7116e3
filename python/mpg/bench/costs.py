"""`mpg-bench costs`: per-render statistics as a table like MPG Table 2.

Each integrator entry renders each scene once (seed 0) with the given budget;
the table shows whatever of these statistics keys the image reports, "–" for the
absent ones (documented in docs/results.md):

    spp, spp_training        samples per pixel: the image's (rendering) and training's
    seconds, seconds_training  wall time: total and in training
    seconds_guide            time querying the guiding distributions (STree query, sampling
                             n, tau and omega from a leaf; core timer guide_ns)
    guide_overhead           seconds_guide / CPU time of the rendering part (wall x threads)
    seconds_bernoulli        time in Bernoulli trials (reciprocal-probability estimation; bernoulli_ns)
    seconds_specular         total time in specular-chain sampling
    subpath_samples          sub-path samples collected for training
    activation_rate          fraction of the chain estimates started that selective activation let run
    bernoulli_trials         number of extra trials spent estimating 1/P
    max_chain_K, max_chain_G the Bernoulli count K and geometry term G of the largest single
                             chain estimate of the render (where the heavy tail comes from)

seconds_guide / seconds_bernoulli / seconds_specular are CPU seconds summed over the
render threads (what a thread can measure); `seconds` is wall time. When an
integrator reports `chain_ns` (nanoseconds in chain estimation, summed over
threads; the sms integrators do) and no seconds_specular, seconds_specular is
chain_ns / 1e9.
"""

from __future__ import annotations

import os
from typing import Any

from mpg.bench import report
from mpg.bench.compare import skip_reason
from mpg.bench.runners import BenchError, IntegratorSpec, log, run_mitsuba, run_mpg
from mpg.bench.scenes import BenchScene
from mpg.errors import MPGError

COLUMNS = [
    # (key, header)
    ("spp", "spp training + rendering"),
    ("seconds", "time (s)"),
    ("seconds_training", "training (s)"),
    ("seconds_guide", "guide (s)"),
    ("seconds_bernoulli", "Bernoulli trials (s)"),
    ("seconds_specular", "specular total (s)"),
    ("guide_overhead", "guide / render CPU"),
    ("subpath_samples", "sub-path samples"),
    ("activation_rate", "activation rate"),
    ("bernoulli_trials", "Bernoulli trials (count)"),
    ("samples_per_second", "samples/s"),
    ("max_chain_K", "largest estimate: K"),
    ("max_chain_G", "largest estimate: G"),
]
STAT_KEYS = [k for k, _ in COLUMNS] + ["spp_training"]


def derived(st: dict[str, Any]) -> dict[str, Any]:
    st = dict(st)
    if st.get("seconds_specular") is None and st.get("chain_ns") is not None:
        st["seconds_specular"] = float(st["chain_ns"]) * 1e-9
    if st.get("seconds_bernoulli") is None and st.get("bernoulli_ns") is not None:
        st["seconds_bernoulli"] = float(st["bernoulli_ns"]) * 1e-9
    if st.get("seconds_guide") is None and st.get("guide_ns") and st.get("integrator") == "mpg":
        st["seconds_guide"] = float(st["guide_ns"]) * 1e-9
    if st.get("seconds_guide") is not None:
        # guiding overhead: guide CPU time over the rendering part's CPU time
        wall = float(st.get("seconds") or 0.0) - float(st.get("seconds_training") or 0.0)
        threads = int(st.get("threads") or 0) or (os.cpu_count() or 1)
        if wall > 0:
            st["guide_overhead"] = float(st["seconds_guide"]) / (wall * threads)
    return st


def _spp_cell(st: dict[str, Any]) -> str:
    """"training + rendering" spp. An image's spp are its rendering passes'
    alone (mpg's training passes are never splatted into it; the paper's
    "n + m" form)."""
    spp = st.get("spp")
    if spp is None:
        return report.DASH
    tr = st.get("spp_training")
    if tr is None:
        return f"{report.DASH} + {report.fmt(int(spp))}"
    return f"{report.fmt(int(tr))} + {report.fmt(int(spp))}"


def run(scenes: list[BenchScene], specs: list[IntegratorSpec], time: float | None,
        spp: int | None, out: str, argv, threads: int | None = None) -> dict[str, Any]:
    if (time is None) == (spp is None):
        raise BenchError("give one of --time and --spp")
    results: dict[str, Any] = {"command": report.command_line(argv), "time": time, "spp": spp,
                               "rows": [], "skipped": []}
    rows = []
    for sc in scenes:
        for spec in specs:
            why = skip_reason(spec)
            if why:
                log(f"mpg-bench: skipping {spec.text}: {why}")
                results["skipped"].append({"scene": sc.label, "integrator": spec.text,
                                           "reason": why})
                continue
            try:
                if spec.backend == "mitsuba":
                    if time is not None:
                        (r,), _ = run_mitsuba(spec, sc, checkpoints=[time])
                    else:
                        (r,), _ = run_mitsuba(spec, sc, spp=spp, passes=min(spp, 8))
                    st = dict(r.stats)
                    st["samples_per_second"] = (r.spp * r.rgb.shape[0] * r.rgb.shape[1]
                                                / r.seconds if r.seconds > 0 else None)
                else:
                    r = run_mpg(spec, sc, time=time, spp=spp, seed=0, threads=threads)
                    st = derived(r.stats)
            except MPGError as e:
                log(f"mpg-bench: skipping {spec.text} on {sc.label}: {e}")
                results["skipped"].append({"scene": sc.label, "integrator": spec.text,
                                           "reason": str(e)})
                continue
            log(f"[costs] {sc.label} {spec.text}: {r.seconds:.2f} s, {r.spp} spp")
            picked = {k: st.get(k) for k in STAT_KEYS}
            results["rows"].append({"scene": sc.to_json(), "integrator": spec.text,
                                    "stats": picked, "all_stats": st})
            chains = sc.sidecar.get("chains")
            if isinstance(chains, list | tuple):
                chains = ", ".join(str(c) for c in chains)
            row = [sc.label, str(chains) if chains else report.DASH, spec.text, _spp_cell(st)]
            row += [report.fmt(st.get(k)) for k, _ in COLUMNS[1:]]
            rows.append(row)
    header = ["scene", "chains", "integrator"] + [h for _, h in COLUMNS]
    budget = f"{time:g} s" if time is not None else f"{spp} spp"
    md = [report.header("Costs per render (like MPG Table 2)", argv),
          (f"One render per scene and integrator, budget {budget}, seed 0. "
           "\"–\": the integrator does not report that statistic.\n"),
          report.md_table(header, rows, ["l", "l", "l"] + ["r"] * (len(header) - 3))]
    for sk in results["skipped"]:
        md.append(f"\n*{sk['integrator']} on {sk['scene']} skipped: {sk['reason']}*")
    _plot(os.path.join(out, "costs.png"), results)
    md.append("\n![time split](costs.png)\n")
    report.write_json(os.path.join(out, "results.json"), results)
    report.write_text(os.path.join(out, "report.md"), "\n".join(md))
    return results


def _plot(path: str, results: dict[str, Any]) -> None:
    """Stacked bars of each render's time: guide, Bernoulli, rest of specular, other."""
    p = report.plt()
    rows = results["rows"]
    fig, ax = p.subplots(figsize=(max(4.0, 1.2 * len(rows) + 2), 3.6))
    labels, parts = [], {"guide": [], "Bernoulli trials": [], "other specular": [], "other": []}
    for r in rows:
        st = r["stats"]
        # CPU seconds: the specular timers are summed over threads
        threads = int(r.get("all_stats", {}).get("threads") or 0) or (os.cpu_count() or 1)
        tot = float(st.get("seconds") or 0.0) * threads
        g = float(st.get("seconds_guide") or 0.0)
        b = float(st.get("seconds_bernoulli") or 0.0)
        s = float(st.get("seconds_specular") or 0.0)
        parts["guide"].append(g)
        parts["Bernoulli trials"].append(b)
        parts["other specular"].append(max(s - g - b, 0.0))
        parts["other"].append(max(tot - max(s, g + b), 0.0))
        labels.append(f"{r['scene']['name']}\n{r['integrator']}")
    bottom = [0.0] * len(rows)
    for name, vals in parts.items():
        ax.bar(range(len(rows)), vals, bottom=bottom, label=name)
        bottom = [a + b for a, b in zip(bottom, vals)]
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels(labels, fontsize=7)
    ax.set_ylabel("CPU seconds (wall x threads)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    p.close(fig)

