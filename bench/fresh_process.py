"""Equal-time renders as `mpg-render` runs them: one fresh process per render.

`ab_params.py` and `mpg-bench compare` render many times in one process, so
every render but the first runs warm (caches, allocator, thread start).
A short render from the command line is always the first: on the sphere at
1 s its first training iteration took 0.13-0.16 s against ~0.1 s warm, and
that decided whether a second one fitted (docs/results.md, fortieth
session). This script runs `mpg-render` once per render, the variants
interleaved per seed (rotated as in ab_params.py), and prints per variant
the MSE against the cached reference, the seeds' variance
(mpg.metrics.seed_variance), the spp and, for `mpg`, the renders' training
spp with the MSE of each group.

    python bench/fresh_process.py sphere --time 1 --seeds 32 --variants '{}' '{"training_continue": false}'
    python bench/fresh_process.py sphere --time 1 --seeds 32 --integrator path --variants '{}'
    python bench/fresh_process.py double_slabs --time 1 --seeds 32 --baseline HEAD

With --baseline REV every variant also runs with the Python package of git
revision REV (`git archive` of python/mpg into a temporary folder, beside
the built core; REV's cpp/ must equal the working tree's), interleaved with
the working tree's: a change without a switch (a faster loop) measured in
one run. Every variant after the first also gets a paired mean-MSE ratio
with a 95 % bootstrap interval over the seeds (above 1: it is the lower;
results file: "paired", with "against"): a REV run against the same
variant's tree run, a tree run against the first variant's. Per render it
also records `seconds_between_passes`, the render's wall time outside the
core's passes (mpg's maps, guides, bookkeeping).

Each variant is a JSON object of integrator parameters ('{}': the
defaults), passed as -P NAME=VALUE. Needs the scene's reference in the
cache (mpg-bench reference). Writes bench/results/fresh_process-<scene>-<hash>.json
after every seed (or --out FILE)."""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import shlex
import shutil
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from mpg import metrics
    from mpg.bench import reference as refmod
    from pixel_errors import add_param_option, load_with_reference, parse_variants, scene_params   # bench/

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="mpg")
    ap.add_argument("--time", type=float, default=1.0)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--first-seed", type=int, default=0, help="the seeds are FIRST-SEED, FIRST-SEED + 1, ...")
    add_param_option(ap)
    ap.add_argument("--variants", nargs="+", default=["{}"], metavar="JSON")
    ap.add_argument("--baseline", metavar="REV",
                    help="also run every variant with git revision REV's python/mpg (its cpp/ as the tree's)")
    ap.add_argument("--out", help="results file (default bench/results/fresh_process-<scene>-<hash>.json)")
    args = ap.parse_args()
    if not args.time > 0:
        ap.error("--time must be > 0")
    if args.seeds < 2:
        ap.error("--seeds must be >= 2 (a seeds' variance)")
    variants = parse_variants(ap, args.variants, "integrator parameters")
    params = scene_params(ap, args)
    loaded = load_with_reference(args.scene, params, "fresh_process")
    if loaded is None:
        return 1
    bs, _, info = loaded
    ref = refmod.load_reference(info)[0].astype(float)
    exe = pathlib.Path(sys.executable).parent / "mpg-render"   # (this Python's, else the PATH's)
    if not exe.is_file():
        found = shutil.which("mpg-render")
        if found is None:
            print("fresh_process: no mpg-render beside this Python nor on the PATH", file=sys.stderr)
            return 1
        exe = pathlib.Path(found)
    command = shlex.join(["python", "bench/fresh_process.py"] + sys.argv[1:])
    key = hashlib.sha1(json.dumps([args.scene, params, args.integrator, args.time, args.seeds,
                                   variants, args.baseline] + ([args.first_seed] if args.first_seed else []))
                       .encode()).hexdigest()
    # (variant, code): code None the working tree's, else a folder holding REV's mpg
    base_dir = tempfile.TemporaryDirectory() if args.baseline else None
    runs_of = [(v, None) for v in variants]
    if base_dir is not None:
        code = baseline_code(args.baseline, pathlib.Path(base_dir.name))
        if code is None:
            return 1
        runs_of = [x for v in variants for x in ((v, None), (v, code))]
    out_path = (pathlib.Path(args.out) if args.out else
                ROOT / "bench" / "results" / f"fresh_process-{pathlib.Path(args.scene).stem}-{key[:10]}.json")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    runs: list[list[dict]] = [[] for _ in runs_of]
    images: list[list[np.ndarray]] = [[] for _ in runs_of]
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            n = len(runs_of)
            for i in [(seed + j) % n for j in range(n)]:
                variant, code = runs_of[i]
                exr, stats = pathlib.Path(tmp) / f"{i}.exr", pathlib.Path(tmp) / f"{i}.json"
                launch = [str(exe)] if code is None else [sys.executable, "-c", LAUNCH, str(code)]
                cmd = launch + [str(bs.path), "--integrator", args.integrator, "--time", str(args.time),
                       "--seed", str(seed), "-o", str(exr), "--no-preview", "-q", "--stats", str(stats)]
                cmd += [a for d in bs.params.items() for a in ("-D", f"{d[0]}={d[1]}")]
                cmd += [a for p in variant.items() for a in ("-P", f"{p[0]}={json.dumps(p[1]).strip(chr(34))}")]
                r = subprocess.run(cmd, capture_output=True, text=True)
                if r.returncode != 0:
                    print(f"fresh_process: {shlex.join(cmd)} failed:\n{r.stderr}", file=sys.stderr)
                    return 1
                rgb = mpg.read_exr(str(exr))[0].astype(float)
                st = json.loads(stats.read_text())
                runs[i].append({"seed": seed, "spp": st["spp"], "spp_training": st.get("spp_training"),
                                "training_continued_spp": st.get("training_continued_spp"),
                                "seconds_between_passes": st.get("seconds_between_passes"),
                                "mse": float(((rgb - ref) ** 2).mean())})
                images[i].append(rgb)
            out = {"command": command, "scene": args.scene, "integrator": args.integrator, "params": params,
                   "time": args.time, "variants": []}
            for (v, code), rs, ims in zip(runs_of, runs, images):
                groups: dict = {}
                for r in rs:
                    groups.setdefault(str(r["spp_training"]), []).append(r["mse"])
                out["variants"].append({
                    "variant": v, "code": args.baseline if code is not None else "tree", "runs": rs, "mse": float(np.mean([r["mse"] for r in rs])),
                    "seed_variance": metrics.seed_variance(np.stack(ims)) if len(ims) > 1 else None,
                    "spp": float(np.mean([r["spp"] for r in rs])),
                    "seconds_between_passes": (float(np.mean([r["seconds_between_passes"] for r in rs]))
                                               if all(r["seconds_between_passes"] is not None for r in rs)
                                               else None),
                    "mse_by_training_spp": {k: {"renders": len(g), "mse": float(np.mean(g))}
                                            for k, g in sorted(groups.items(), key=lambda kv: float(kv[0])
                                                               if kv[0] != "None" else -1.0)}})
            # (a REV run against the same variant's tree run; a tree run
            # against the first variant's)
            for v in out["variants"][1:]:
                partner = next(u for u in out["variants"] if u["variant"] == v["variant"]) \
                    if v["code"] != "tree" else out["variants"][0]
                if partner is not v:
                    v["paired"] = dict(paired_ratio(partner["runs"], v["runs"]),
                                       against={"variant": partner["variant"], "code": partner["code"]})
            out_path.write_text(json.dumps(out, indent=1))
    for v in out["variants"]:
        tr = "" if args.integrator != "mpg" else "; by training spp: " + ", ".join(
            f"{k}: {g['renders']} renders, MSE {g['mse']:.4g}" for k, g in v["mse_by_training_spp"].items())
        between = ("" if v["seconds_between_passes"] is None
                   else f", {v['seconds_between_passes']:.3f} s between passes")
        code = "" if args.baseline is None else f" [{v['code']}]"
        print(f"== {json.dumps(v['variant'])}{code}: MSE {v['mse']:.4g} seed var. {v['seed_variance']:.4g} "
              f"spp {v['spp']:.1f}{between}{tr}")
        pr = v.get("paired")
        if pr is not None:
            ag = pr["against"]
            label = json.dumps(ag["variant"]) + ("" if args.baseline is None else f" [{ag['code']}]")
            print(f"   MSE of {label} over this one: {pr['ratio']:.3f}, 95 % interval "
                  f"[{pr['ci95'][0]:.3f}, {pr['ci95'][1]:.3f}] ({pr['seeds']} paired seeds; above 1: this one lower)")
    print(f"wrote {out_path}")
    return 0


def paired_ratio(first: list[dict], other: list[dict], draws: int = 20_000) -> dict:
    """The first variant's mean MSE over the other's, on the seeds both
    rendered, with a 95 % percentile-bootstrap interval: the seeds are
    resampled with replacement, each draw's pair kept together (a seed's
    scene noise is shared), and the ratio of the two means taken per draw.
    Above 1 the other is better. A fixed generator: the same runs give the
    same interval."""
    a = {r["seed"]: r["mse"] for r in first}
    b = {r["seed"]: r["mse"] for r in other}
    seeds = sorted(set(a) & set(b))
    x = np.array([a[s] for s in seeds], dtype=float)
    y = np.array([b[s] for s in seeds], dtype=float)
    if len(seeds) < 2 or not np.all(y > 0):
        return {"seeds": len(seeds), "ratio": float("nan"), "ci95": [float("nan"), float("nan")]}
    idx = np.random.default_rng(0).integers(0, len(seeds), (draws, len(seeds)))
    boot = x[idx].mean(axis=1) / y[idx].mean(axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return {"seeds": len(seeds), "ratio": float(x.mean() / y.mean()), "ci95": [float(lo), float(hi)]}


# Runs mpg.cli with the package in argv[1] (the editable install's finder,
# which would import the working tree's, taken out of sys.meta_path first).
LAUNCH = (
    "import sys; sys.meta_path[:] = [f for f in sys.meta_path if 'skbc' not in type(f).__module__ "
    "and 'editable' not in type(f).__module__.lower()]; "
    "sys.path.insert(0, sys.argv.pop(1)); "
    "import mpg; assert mpg.__file__.startswith(sys.path[0]), mpg.__file__; "
    "from mpg.cli import main; sys.argv[0] = 'mpg-render'; sys.exit(main())")


def baseline_code(rev: str, dest: pathlib.Path) -> pathlib.Path | None:
    """REV's python/mpg in dest/mpg with the built core beside it; None (said)
    where REV's cpp/ differs from the working tree's, or git fails."""
    from mpg import _core

    diff = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", rev, "--", "cpp", "CMakeLists.txt"])
    if diff.returncode != 0:
        print(f"fresh_process: {rev}'s cpp/ differs from the working tree's (or git failed): "
              f"its Python would run on this core", file=sys.stderr)
        return None
    arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "python/mpg"], capture_output=True)
    if arch.returncode != 0:
        print(f"fresh_process: git archive {rev}: {arch.stderr.decode().strip()}", file=sys.stderr)
        return None
    subprocess.run(["tar", "-x", "-C", str(dest)], input=arch.stdout, check=True)
    core = pathlib.Path(_core.__file__)
    (dest / "python" / "mpg" / core.name).symlink_to(core)
    return dest / "python"


if __name__ == "__main__":
    sys.exit(main())
