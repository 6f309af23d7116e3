"""Markdown tables for docs/results.md from the folders that `mpg-bench compare`
and `mpg-bench curves` wrote (their results.json).

    python bench/results_tables.py bench/results/compare-default bench/results/curves-default
"""

from __future__ import annotations

import json
import pathlib
import sys


def scene_name(s: dict) -> str:
    sc = s["scene"]
    return sc["name"] if isinstance(sc, dict) else str(sc)


def integrator_names(r: dict) -> list[str]:
    """Integrators of a results.json, in order of first appearance."""
    names: list[str] = []
    for s in r["scenes"]:
        for m in s["methods"]:
            if m["integrator"] not in names:
                names.append(m["integrator"])
    return names


def fmt(x: float) -> str:
    return f"{x:.3g}"


def compare_table(folder: pathlib.Path) -> str:
    r = json.loads((folder / "results.json").read_text())
    names = integrator_names(r)
    out = [f"relMSE whole image / caustic box, mean over {r['seeds']} seeds, {r['time']} s per render "
           f"(`{r.get('command', '')}`):", "",
           "| scene | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for s in r["scenes"]:
        cells = []
        by = {m["integrator"]: m["summary"] for m in s["methods"]}
        for n in names:
            if n not in by:
                cells.append("–")
                continue
            im = by[n]["image"]["relmse"]["mean"]
            ca = ((by[n].get("caustic") or {}).get("relmse") or {}).get("mean")
            cells.append(fmt(im) + (f" / {fmt(ca)}" if ca is not None else ""))
        out.append(f"| {scene_name(s)} | " + " | ".join(cells) + " |")
    out += ["", "MAPE whole image (robust to fireflies):", "",
            "| scene | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for s in r["scenes"]:
        by = {m["integrator"]: m["summary"] for m in s["methods"]}
        out.append(f"| {scene_name(s)} | " + " | ".join(
            fmt(by[n]["image"]["mape"]["mean"]) if n in by else "–" for n in names) + " |")
    return "\n".join(out)


def curves_table(folder: pathlib.Path) -> str:
    r = json.loads((folder / "results.json").read_text())
    names = integrator_names(r)
    out = [f"Seconds to reach the path tracer's relMSE at {max(r['times'])} s in the caustic box "
           f"(`*` extrapolated, error ~ 1/t; `{r.get('command', '')}`):", "",
           "| scene | target relMSE | " + " | ".join(names) + " |", "|---|---:|" + "---:|" * len(names)]
    for s in r["scenes"]:
        t = s.get("time_to_target_caustic") or s.get("time_to_target_image")
        if not t:
            continue
        cells = []
        for n in names:
            v = t["methods"].get(n)
            if not v or v.get("seconds") is None:
                cells.append("not reached")
            else:
                cells.append(fmt(v["seconds"]) + ("*" if v.get("extrapolated") else ""))
        out.append(f"| {scene_name(s)} | {fmt(t['target_relmse'])} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main() -> int:
    for arg in sys.argv[1:]:
        folder = pathlib.Path(arg)
        r = json.loads((folder / "results.json").read_text())
        print(curves_table(folder) if "times" in r else compare_table(folder))
        print()
    return 0


if __name__ == "__main__" and "--solver" not in sys.argv:
    sys.exit(main())


def solver_table(folder: pathlib.Path) -> str:
    """Walk success rate and mean Bernoulli count per scene from a `costs` run."""
    r = json.loads((folder / "results.json").read_text())
    out = [f"Manifold-walk success and Bernoulli trials (`{r.get('command', '')}`):", "",
           "| scene | integrator | first-trial success | mean trials K per estimate | capped | "
           "top walk failures |", "|---|---|---:|---:|---:|---|"]
    for row in r["rows"]:
        st = row.get("all_stats") or {}
        est = st.get("chain_estimates", 0)
        if not est:
            continue
        conv = st.get("chain_converged", 0)
        contrib = st.get("chain_contributions", 0)
        trials = st.get("bernoulli_trials", 0)
        fails = sorted(((v, k[len("walk_fail_"):]) for k, v in st.items()
                        if k.startswith("walk_fail_") and v), reverse=True)[:2]
        out.append(f"| {scene_name(row)} | {row['integrator']} | {conv / est:.3f} | "
                   f"{(1 + trials / contrib) if contrib else float('nan'):.2f} | "
                   f"{st.get('bernoulli_capped', 0)} | "
                   + ", ".join(f"{k} {v / est:.2f}" for v, k in fails) + " |")
    return "\n".join(out)


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "--solver":
    print(solver_table(pathlib.Path(sys.argv[2])))
