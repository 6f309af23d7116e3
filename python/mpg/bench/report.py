"""Output folders, statistics over seeds, Markdown tables, JSON and figures."""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

DASH = "–"


def out_dir(command: str, arg: str | None) -> str:
    if arg:
        d = arg
    else:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        d = os.path.join("bench", "results", f"{command}-{stamp}")
    os.makedirs(d, exist_ok=True)
    return os.path.abspath(d)


def spread(values: Sequence[float]) -> dict[str, Any]:
    """Mean, sample standard deviation (ddof=1; 0 for one value), min, max over seeds."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "min": float(v.min()), "max": float(v.max()), "n": int(v.size)}


def fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return DASH
    if isinstance(x, bool):
        return str(x)
    if isinstance(x, int | np.integer):
        return f"{int(x):,}".replace(",", " ")
    if isinstance(x, float | np.floating):
        if not math.isfinite(float(x)):
            return str(float(x))
        if x == 0:
            return "0"
        if 1e-3 <= abs(x) < 1e4:
            return f"{x:.{digits}g}"
        return f"{x:.{max(digits - 1, 1)}e}"
    return str(x)


def fmt_spread(s: dict[str, Any] | None) -> str:
    if not s or s.get("mean") is None:
        return DASH
    if s.get("n", 1) > 1:
        return f"{fmt(s['mean'])} ± {fmt(s['std'], 2)}"
    return fmt(s["mean"])


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]],
             align: Sequence[str] | None = None) -> str:
    align = align or ["l"] + ["r"] * (len(header) - 1)
    sep = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(sep) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(c) for c in r) + " |")
    return "\n".join(lines)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(path: str, data: Any) -> None:
    with open(path, "w") as f:
        json.dump(_jsonable(data), f, indent=2, default=str)


def write_text(path: str, text: str) -> None:
    with open(path, "w") as f:
        f.write(text.rstrip() + "\n")


def command_line(argv: Sequence[str] | None) -> str:
    import shlex

    args = list(sys.argv[1:] if argv is None else argv)
    return "mpg-bench " + " ".join(shlex.quote(a) for a in args)


def header(title: str, argv: Sequence[str] | None) -> str:
    import platform

    import mpg

    return (f"# {title}\n\n"
            f"Made {_dt.datetime.now().isoformat(timespec='seconds')} on {platform.node()} "
            f"({os.cpu_count()} cores), mpg {mpg.__version__}, by:\n\n"
            f"```sh\n{command_line(argv)}\n```\n")


# ---------------------------------------------------------------- figures


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as p

    return p


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    from mpg.image import to_srgb8

    return to_srgb8(rgb, exposure)


def side_by_side(path: str, title: str, ref: np.ndarray, images: list[tuple[str, np.ndarray, str]],
                 box: Sequence[float] | None, exposure: float = 0.0) -> None:
    """Reference then one column per method: full image on top, the caustic-box crop
    (nearest-neighbour enlarged) under it; labels carry the method and its error."""
    from mpg.metrics import box_to_slices

    p = plt()
    cols = [("reference", ref, "")] + list(images)
    n = len(cols)
    rows = 2 if box is not None else 1
    fig, axes = p.subplots(rows, n, figsize=(2.6 * n, 2.9 * rows), squeeze=False)
    h, w = ref.shape[:2]
    if box is not None:
        rs, cs = box_to_slices((h, w), box)
    for j, (name, img, label) in enumerate(cols):
        ax = axes[0][j]
        ax.imshow(tonemap(img, exposure), interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        if box is not None:
            from matplotlib.patches import Rectangle

            ax.add_patch(Rectangle((cs.start - 0.5, rs.start - 0.5), cs.stop - cs.start,
                                   rs.stop - rs.start, fill=False, edgecolor="#ff4040", lw=1))
            ax2 = axes[1][j]
            ax2.imshow(tonemap(img[rs, cs], exposure), interpolation="nearest")
            ax2.set_xticks([])
            ax2.set_yticks([])
            if j == 0:
                ax2.set_ylabel("caustic box", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    p.close(fig)
