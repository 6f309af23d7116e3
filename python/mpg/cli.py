"""mpg-render: render a Mitsuba scene file (or the built-in default scene)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from collections.abc import Sequence

from mpg.errors import MPGError


def _parse_define(s: str) -> tuple[str, str]:
    if "=" not in s:
        raise argparse.ArgumentTypeError(f"-D expects name=value, got '{s}'")
    k, v = s.split("=", 1)
    if not k:
        raise argparse.ArgumentTypeError(f"-D expects name=value, got '{s}'")
    return k, v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mpg-render",
        description="Render a Mitsuba 2/3 scene file with mpg. Without SCENE, renders the "
        "built-in default scene (a glass sphere casting a caustic).",
    )
    p.add_argument("scene", nargs="?", help="scene file (Mitsuba XML)")
    p.add_argument("-o", "--output", help="output EXR (default: out/<scene name>.exr)")
    p.add_argument("-D", dest="defines", action="append", type=_parse_define, default=[],
                   metavar="NAME=VALUE", help="override a <default> value of the scene")
    p.add_argument("--integrator", help="integrator name: path, sms, sms_star, mpg (default: the scene's)")
    p.add_argument("-P", dest="iparams", action="append", type=_parse_define, default=[],
                   metavar="NAME=VALUE",
                   help="integrator parameter, e.g. -P tau=TT -P max_depth=8 -P chain_rate=1 (repeatable)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--spp", type=int, help="samples per pixel (default: the scene's sampler)")
    g.add_argument("--time", type=float, help="time budget in seconds")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--sampler", choices=("independent", "stratified"),
                   help="pixel positions: independent, or stratified (a shifted Sobol sequence "
                        "per pixel); default: the scene's <sampler>")
    p.add_argument("--threads", type=int, help="render threads (default: all cores)")
    p.add_argument("--preview", help="also write a tone-mapped PNG (default: beside the EXR)")
    p.add_argument("--no-preview", action="store_true", help="do not write a PNG")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    p.add_argument("--stats", help="write the render statistics as JSON")
    p.add_argument("--chain-rate-map", metavar="PNG",
                   help="mpg: write the learned per-pixel chain rates as a grey PNG "
                        "(log2 scale, black 1/32 .. white 1)")
    p.add_argument("--substitute-missing-textures", action="store_true",
                   help="replace missing texture files by neutral stand-ins (with a warning)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    return p


def _raise_interrupt(signum, frame):  # SIGTERM behaves like Ctrl-C: stop and write
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except MPGError as e:
        print(f"mpg-render: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\nmpg-render: interrupted before rendering started; nothing written",
              file=sys.stderr)
        return 130


def _run(args) -> int:
    import mpg

    if args.spp is not None and args.spp < 1:
        raise MPGError(f"--spp must be at least 1, got {args.spp}")
    if args.time is not None and not args.time > 0:
        raise MPGError(f"--time must be positive, got {args.time}")
    if args.threads is not None and args.threads < 1:
        raise MPGError(f"--threads must be at least 1, got {args.threads}")
    path = args.scene or mpg.default_scene_path()
    name = "default" if args.scene is None else os.path.splitext(os.path.basename(path))[0]
    if args.scene is not None and not os.path.isfile(path):
        raise MPGError(f"{path}: no such scene file")
    out = args.output or os.path.join("out", name + ".exr")
    if not out.lower().endswith(".exr"):
        raise MPGError(f"-o {out}: the output must be an .exr file (use --preview for PNG)")
    preview = None if args.no_preview else (args.preview or os.path.splitext(out)[0] + ".png")

    defines = dict(args.defines)
    scene = mpg.load_file(path, substitute_missing_textures=args.substitute_missing_textures,
                          **defines)
    for w in scene.warnings:
        print(f"mpg-render: warning: {w}", file=sys.stderr)
    if not args.quiet:
        cam = scene.desc.camera
        print(f"mpg-render: {path}: {len(scene.desc.shapes)} shapes, "
              f"{cam.crop[2]}x{cam.crop[3]} pixels", file=sys.stderr)
    old = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        integrator = args.integrator
        if args.iparams:
            base = args.integrator or scene.desc.integrator.type
            # a -P name no integrator of mpg has is an error (a typo would run the
            # defaults); the scene file's own parameters only warn
            from mpg.render import check_param_names
            from mpg.scene.desc import IntegratorDesc
            check_param_names(base, dict(args.iparams))
            if base == scene.desc.integrator.type:
                integrator = IntegratorDesc(base, {**scene.desc.integrator.params, **dict(args.iparams)})
            else:
                integrator = {"type": base, **dict(args.iparams)}
        img = mpg.render(scene, integrator=integrator, spp=args.spp, time=args.time,
                         seed=args.seed, threads=args.threads, sampler=args.sampler,
                         progress=False if args.quiet else None)
    finally:
        signal.signal(signal.SIGTERM, old)
    for w in img.stats.get("warnings", []):
        if w not in scene.warnings:
            print(f"mpg-render: warning: {w}", file=sys.stderr)
    img.write_exr(out)
    if preview:
        img.write_png(preview, exposure=args.exposure)
    if args.chain_rate_map:
        if img.chain_rate_map is None:
            print("mpg-render: warning: no learned chain rates to write (not mpg, no chain work, "
                  "a fixed chain_rate or too little training)", file=sys.stderr)
        else:
            from mpg.chain_rates import rate_map_grey8
            from mpg.image import write_png8
            write_png8(args.chain_rate_map, rate_map_grey8(img.chain_rate_map))
            if img.stats.get("handoff_all", 0) > 0:
                print(f"mpg-render: note: every pixel was handed to the path tracer (handoff_all="
                      f"{'auto, ' if img.stats.get('handoff_all_mode') == 'auto' else ''}{img.stats['handoff_all']}): "
                      f"the chain rate map written is 0 everywhere (-P handoff_all=0 renders the learned one)",
                      file=sys.stderr)
    if args.stats:
        stats = dict(img.stats)
        stats["scene"] = os.path.abspath(path)
        stats["output"] = os.path.abspath(out)
        os.makedirs(os.path.dirname(os.path.abspath(args.stats)), exist_ok=True)
        with open(args.stats, "w") as f:
            json.dump(stats, f, indent=2, default=str)
    st = img.stats
    if not args.quiet or st["interrupted"]:
        state = ""
        if st["interrupted"]:
            state = " (interrupted: partial image)"
        elif st["time_limited"]:
            cut = st.get("seconds_dropped", 0.0)
            state = (f" (time limit reached; the pass it cut, {cut:.1f} s, dropped)" if cut >= 0.05
                     else " (time limit reached)")
        print(f"mpg-render: wrote {out}" + (f" and {preview}" if preview else "")
              + f": {img.spp} spp, {st['seconds']:.2f} s, "
              f"{st['samples_per_second'] / 1e6:.2f} M samples/s{state}", file=sys.stderr)
        if st.get("integrator") == "mpg" and st.get("training_iterations", 0) > 0:
            auto_all = st.get("handoff_all_mode") == "auto" and "handoff_all_model_ratio" in st
            why_all = (f"handoff_all=auto: the rates' model put it at {st['handoff_all_model_ratio']:.2g}x "
                       f"their maps' variance x time" if auto_all else "handoff_all")
            rates = (f"every pixel handed to the path tracer with {st['handoff_all']} guided traces "
                     f"({why_all}; the learned rates not used)" if st.get("handoff_all", 0) > 0 else
                     f"chain rates per pixel: mean {st['chain_rate_mean']:.3f}, "
                     f"{100 * st['chain_rate_fraction_one']:.0f} % at 1, "
                     f"{100 * st.get('chain_rate_fraction_pt', 0.0):.0f} % to the path tracer"
                     + (f" ({100 * st['chain_rate_fraction_trace']:.0f} % with guided traces, "
                        f"mean {st.get('guided_trace_mean_k', 0.0):.1f})"
                        if st.get("chain_rate_fraction_trace", 0.0) > 0 else "")
                     + (f" (hand-off {st['chain_handoff']})"
                        if str(st.get("chain_handoff", "")).startswith("off:") else "")
                     + (f" (handoff_all=auto kept them: the rates' model put every pixel handed off "
                        f"at {st['handoff_all_model_ratio']:.2g}x their variance x time)" if auto_all else "")
                     if st.get("chain_rate_mode") == "per-pixel"
                     else f"chain rate {st['chain_rate_mean']:g}")
            if st.get("delta_split", "off") != "off":
                rates += (f"; light seen in the glass split in "
                          f"{100 * st.get('delta_split_fraction', 1.0):.1f} % of the pixels "
                          f"(mean {st.get('delta_split_mean', 0.0):.1f} paths)"
                          + (", then in every pixel that sees glass (the render's own samples chose it)"
                             if st.get("delta_split_online_glass") else "")
                          + (f", {100 * st['delta_split_online_measured']:.0f} % of them at counts "
                             f"from their paths' own variance (mean {st['delta_split_online_measured_mean']:.1f}, "
                             f"up to {st.get('delta_split_online_measured_max', 0.0):.0f})"
                             if st.get("delta_split_online_measured", 0.0) > 0.0 else ""))
            if st.get("pixel_split", "off") != "off":
                rates += (f"; pixels split ({st['pixel_split']}) in "
                          f"{100 * st.get('pixel_split_fraction', 1.0):.1f} % of the pixels "
                          f"(mean {st.get('pixel_split_mean', 0.0):.1f} samples"
                          + (f", cost per sample capped at {st['pixel_split_cost']:.2f}x from "
                             f"{st['pixel_split_capped']:.2f}x" if "pixel_split_capped" in st else "")
                          + ")"
                          + (f", refined {st['pixel_split_online_updates']} times by the render's own samples "
                             f"to {100 * st.get('pixel_split_online_fraction', 0.0):.1f} % "
                             f"(mean {st.get('pixel_split_online_mean', 0.0):.1f})"
                             if st.get("pixel_split_online_updates") else ""))
            if st.get("chain_unknown_type"):
                rates += (f"; {st['chain_unknown_type']} chains of types their leaf never saw "
                          f"left to the path tracer")
            cont = st.get("training_continued_spp", 0)
            print(f"mpg-render: mpg trained {st['training_iterations']} iterations "
                  f"({st['spp_training']} spp" + (f", {cont} of them continuing the last iteration" if cont else "")
                  + f", {st['seconds_training']:.1f} s), "
                  f"{st['guide_leaves']} leaves; {rates}", file=sys.stderr)
        if st.get("lt_photons"):
            print(f"mpg-render: light traced the caustics the camera sees: {st['lt_photons']} photons, "
                  f"{st.get('lt_splats', 0)} reached the camera ({st.get('lt_chain_splats', 0)} of them "
                  f"through glass)", file=sys.stderr)
        if st.get("glint_seeds"):
            print(f"mpg-render: walked the small lights' glints seen in the glass: {st.get('glint_walks', 0)} "
                  f"walks from {st['glint_seeds']} camera samples, {st.get('glint_found', 0)} found in their "
                  f"pixel ({st.get('glint_pt_dropped', 0)} path-tracer hits left to them)", file=sys.stderr)
        if st.get("glint_rejected"):
            print(f"mpg-render: rejected {st['glint_rejected']} glint estimates with NaN/Inf values",
                  file=sys.stderr)
        if st["rejected_samples"]:
            print(f"mpg-render: rejected {st['rejected_samples']} samples with NaN/Inf/negative "
                  f"values (NaN {st.get('rejected_nan', 0)}, Inf {st.get('rejected_inf', 0)}, "
                  f"negative {st.get('rejected_negative', 0)})", file=sys.stderr)
        if st.get("lt_rejected"):
            print(f"mpg-render: rejected {st['lt_rejected']} light-traced splats with NaN/Inf/negative values",
                  file=sys.stderr)
    if img.spp == 0:
        print("mpg-render: warning: no complete pass; the image is black", file=sys.stderr)
    return 130 if st["interrupted"] else 0


if __name__ == "__main__":
    sys.exit(main())
