"""Benchmark scenes: a scene file, its <default> overrides and its sidecar JSON.

A scene is named on the command line by a path (`scenes/sphere_glass.xml`) or a
name looked up as scenes/eval/NAME.xml, then scenes/NAME.xml (relative to the
current directory, then to the repository). Its sidecar NAME.json beside it
({"name", "description", "chains", "series", "caustic_box": [x0, y0, x1, y1],
"reference": text, "reference_fill": integrator}) is optional: without it
there is no caustic box and the metrics are over the whole image only.
"reference_fill" names an mpg integrator that renders the pixels Mitsuba's
light tracer cannot see, in place of Mitsuba's path tracer (mpg.bench.reference).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from typing import Any

from mpg.errors import MPGError

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(
    __file__)))))


class BenchError(MPGError):
    """A benchmark input the user can fix (unknown scene, bad option, missing reference)."""


@dataclass
class BenchScene:
    path: str                                   # absolute path of the XML file
    name: str                                   # sidecar name or file stem
    params: dict[str, str] = field(default_factory=dict)   # <default> overrides
    sidecar: dict[str, Any] = field(default_factory=dict)

    @property
    def caustic_box(self) -> list[float] | None:
        box = self.sidecar.get("caustic_box")
        return [float(v) for v in box] if box else None

    @property
    def reference_hint(self) -> str:
        return str(self.sidecar.get("reference", "") or "")

    @property
    def reference_fill(self) -> str | None:
        v = self.sidecar.get("reference_fill")
        return str(v) if v else None

    @property
    def label(self) -> str:
        if not self.params:
            return self.name
        return self.name + "[" + ",".join(f"{k}={v}" for k, v in sorted(self.params.items())) + "]"

    def load_mpg(self):
        import mpg

        return mpg.load_file(self.path, **self.params)

    def content_hash(self) -> str:
        """sha256 of the scene file, every file it references that exists, and the params."""
        h = hashlib.sha256()
        for p in referenced_files(self.path):
            h.update(os.path.relpath(p, os.path.dirname(self.path)).encode())
            with open(p, "rb") as f:
                h.update(hashlib.sha256(f.read()).digest())
        h.update(json.dumps(sorted(self.params.items())).encode())
        return h.hexdigest()

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "path": self.path, "params": dict(self.params),
                "caustic_box": self.caustic_box, "chains": self.sidecar.get("chains"),
                "series": self.sidecar.get("series"),
                "description": self.sidecar.get("description")}


_TAG = re.compile(rb"<[A-Za-z][^>]*>")
_ATTR = re.compile(rb'([A-Za-z_]+)\s*=\s*"([^"]*)"')


def _named_files(xml: bytes) -> list[str]:
    """filename="..." attributes and <string name="filename" value="..."/> values."""
    out = []
    for tag in _TAG.findall(xml):
        attrs = dict(_ATTR.findall(tag))
        fn = attrs.get(b"value") if attrs.get(b"name") == b"filename" else attrs.get(b"filename")
        if fn:
            out.append(fn.decode("utf-8", "replace"))
    return out


def referenced_files(path: str, _seen: set[str] | None = None) -> list[str]:
    """The scene file and the files it names (filename="..." values, includes,
    recursively), those that exist, in a stable order. Names with unresolved
    $variables are skipped (they still change the hash through the XML text)."""
    seen = _seen if _seen is not None else set()
    path = os.path.abspath(path)
    if path in seen or not os.path.isfile(path):
        return []
    seen.add(path)
    out = [path]
    if not path.lower().endswith(".xml"):
        return out
    with open(path, "rb") as f:
        data = f.read()
    base = os.path.dirname(path)
    for fn in _named_files(data):
        if "$" in fn:
            continue
        cand = fn if os.path.isabs(fn) else os.path.join(base, fn)
        out.extend(referenced_files(cand, seen))
    return out


def parse_params(items: list[str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for s in items or []:
        if "=" not in s or not s.split("=", 1)[0]:
            raise BenchError(f"--param expects name=value, got '{s}'")
        k, v = s.split("=", 1)
        out[k] = v
    return out


def resolve_scene(spec: str, params: dict[str, str] | None = None) -> BenchScene:
    cands = [spec]
    if not spec.lower().endswith(".xml"):
        for root in (os.getcwd(), REPO):
            cands += [os.path.join(root, "scenes", "eval", spec + ".xml"),
                      os.path.join(root, "scenes", spec + ".xml")]
    for c in cands:
        if os.path.isfile(c):
            path = os.path.abspath(c)
            break
    else:
        raise BenchError(f"scene '{spec}' not found (looked at: {', '.join(cands)})")
    stem = os.path.splitext(path)[0]
    sidecar: dict[str, Any] = {}
    if os.path.isfile(stem + ".json"):
        try:
            with open(stem + ".json") as f:
                sidecar = json.load(f)
        except (OSError, ValueError) as e:
            raise BenchError(f"{stem}.json: cannot read the sidecar: {e}") from None
        if not isinstance(sidecar, dict):
            raise BenchError(f"{stem}.json: the sidecar must be a JSON object")
    name = str(sidecar.get("name") or os.path.basename(stem))
    sc = BenchScene(path=path, name=name, params=dict(params or {}), sidecar=sidecar)
    fill = sidecar.get("reference_fill")
    if fill is not None and (not isinstance(fill, str) or not re.fullmatch(r"[a-z_]+(/[a-z_]+=[^/]+)*",
                                                                            fill)):
        raise BenchError(f"{stem}.json: reference_fill must be an mpg integrator name "
                         f"(e.g. \"sms_star\"), got {fill!r}")
    box = sidecar.get("caustic_box")
    if box is not None:
        from mpg.metrics import MetricError, box_to_slices

        try:
            box_to_slices((100, 100), box)
        except MetricError as e:
            raise BenchError(f"{stem}.json: caustic_box: {e}") from None
    return sc
