"""Mitsuba 2/3 scene XML -> SceneDesc (see desc.py for the contract).

The loader works in two phases:

1. *Expansion*: `<default>` values are collected (overridable by the caller's
   params, like Mitsuba's ``-D``), ``$name`` is substituted in every attribute,
   ``<include>`` files are spliced in (cycles detected) and every ``id`` is
   registered.
2. *Building*: each plugin element is turned into its Desc object. Every
   plugin reads its parameters through `Props`, which remembers what was asked
   for; a parameter nobody asked for is an error naming the supported ones.

Every problem raises SceneError(message, file, line).
"""

from __future__ import annotations

import math
import os
import re
from typing import Any

import numpy as np

from mpg.errors import SceneError
from mpg.scene import shapes as shp
from mpg.scene import spectra
from mpg.scene.desc import (
    BSDFDesc,
    CameraDesc,
    EmitterDesc,
    FilterDesc,
    IntegratorDesc,
    SceneDesc,
    ShapeDesc,
    SourcePos,
    TextureDesc,
)
from mpg.scene.textures import read_image
from mpg.scene.xml_parser import Node, parse_xml

PROPERTY_TAGS = {"float", "integer", "boolean", "string", "rgb", "srgb", "spectrum",
                 "point", "vector", "transform"}
OBJECT_TAGS = {"shape", "bsdf", "texture", "emitter", "sensor", "film", "sampler", "rfilter",
               "integrator", "medium", "phase", "volume"}

SHAPE_HINTS = ("caustic_caster_single", "caustic_caster_multi", "caustic_receiver",
               "caustic_bouncer")
EMITTER_HINTS = ("caustic_emitter_single", "caustic_emitter_multi")

PAPER_INTEGRATORS = ("path_sms_ss", "path_sms_ms", "path_filtered_ss", "path_filtered_ms",
                     "manifold_path_guiding", "sms", "sms_star", "mpg")
# Knobs of the papers' integrators seen in their scenes and scripts; others are
# kept as well, with a warning (they may be typos).
PAPER_KNOBS = {
    "max_depth", "rr_depth", "hide_emitters", "samples_per_pass", "timeout", "biased",
    "twostage", "halfvector_constraints", "mnee_init", "max_iterations", "solver_threshold",
    "uniqueness_threshold", "max_trials", "biased_mnee", "disable_reflected_emitters",
    "train_auto", "guided", "budget_is_time", "spatial_struct", "spatial_filter", "knn_k",
    "directional_struct", "ablation", "product_sampling", "caustics_biased",
    "caustics_twostage", "caustics_halfvector_constraints", "caustics_mnee_init",
    "caustics_max_iterations", "caustics_solver_threshold", "caustics_uniqueness_threshold",
    "caustics_max_trials", "glossy_threshold", "seed", "train_fraction", "selective_activation",
    "training_spp", "train_spp", "bernoulli_cap", "guide_mix", "mixture_components",
}

BSDF_TYPES = ("diffuse", "conductor", "roughconductor", "dielectric", "roughdielectric",
              "thindielectric", "plastic", "roughplastic", "twosided", "normalmap", "null")
SHAPE_TYPES = ("obj", "ply", "serialized", "sphere", "rectangle", "disk", "cube", "cylinder")
EMITTER_TYPES = ("area", "point", "spot", "directional", "constant", "envmap")
TEXTURE_TYPES = ("bitmap", "checkerboard")
INTEGRATOR_TYPES = ("path", "ptracer", "volpath", "direct") + PAPER_INTEGRATORS
SAMPLER_ALIASES = ("stratified", "multijitter", "orthogonal", "ldsampler", "low_discrepancy")

_NUM_SPLIT = re.compile(r"[,\s]+")
_VAR = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


# ---------------------------------------------------------------------------
# Small value parsers

def _numbers(node: Node, s: str, what: str) -> list[float]:
    parts = [t for t in _NUM_SPLIT.split(s.strip()) if t]
    try:
        vals = [float(t) for t in parts]
    except ValueError:
        raise node.error(f"{what}: expected numbers, got '{s}'") from None
    if any(math.isnan(v) for v in vals):
        raise node.error(f"{what}: NaN is not allowed ('{s}')")
    return vals


def _float(node: Node, s: str | None, what: str) -> float:
    if s is None:
        raise node.error(f"{what}: missing 'value' attribute")
    try:
        v = float(s.strip())
    except ValueError:
        raise node.error(f"{what}: expected a number, got '{s}'") from None
    if math.isnan(v):
        raise node.error(f"{what}: NaN is not allowed")
    return v


def _int(node: Node, s: str | None, what: str) -> int:
    if s is None:
        raise node.error(f"{what}: missing 'value' attribute")
    try:
        return int(s.strip())
    except ValueError:
        raise node.error(f"{what}: expected an integer, got '{s}'") from None


def _bool(node: Node, s: str | None, what: str) -> bool:
    if s is None:
        raise node.error(f"{what}: missing 'value' attribute")
    t = s.strip().lower()
    if t == "true":
        return True
    if t == "false":
        return False
    raise node.error(f"{what}: expected 'true' or 'false', got '{s}'")


def _vec3_attr(node: Node, what: str, default: float) -> np.ndarray:
    """A 3-vector from value="x y z" / value="s" or from x, y, z attributes."""
    if "value" in node.attrib:
        if any(k in node.attrib for k in "xyz"):
            raise node.error(f"{what}: give either 'value' or x/y/z, not both")
        v = _numbers(node, node.attrib["value"], what)
        if len(v) == 1:
            return np.full(3, v[0])
        if len(v) != 3:
            raise node.error(f"{what}: expected 1 or 3 numbers, got {len(v)}")
        return np.array(v)
    return np.array([_float(node, node.attrib[k], what) if k in node.attrib else default
                     for k in "xyz"])


def _check_attrs(node: Node, allowed: set[str]) -> None:
    for k in node.attrib:
        if k not in allowed:
            raise node.error(f"unexpected attribute '{k}' on <{node.tag}> "
                             f"(allowed: {', '.join(sorted(allowed))})")


def _finite(node: Node, v: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(v)):
        raise node.error(f"{what}: values must be finite")
    return v


# ---------------------------------------------------------------------------
# Transforms

def translate(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


def scale(v) -> np.ndarray:
    return np.diag([v[0], v[1], v[2], 1.0])


def rotate(axis, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.max(np.abs(a))          # pre-scale: no overflow for huge components
    a = a / np.linalg.norm(a)
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    x, y, z = a
    r = np.array([
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ])
    m = np.eye(4)
    m[:3, :3] = r
    return m


def lookat(origin, target, up) -> np.ndarray | None:
    """Mitsuba's look-at: columns (left, up', dir, origin); None if degenerate."""
    o, t, u = (np.asarray(x, dtype=np.float64) for x in (origin, target, up))
    d = t - o
    dn = np.linalg.norm(d)
    if not dn > 0:
        return None
    d = d / dn
    left = np.cross(u, d)
    ln = np.linalg.norm(left)
    if not ln > 1e-9 * max(np.linalg.norm(u), 1e-300):
        return None
    left = left / ln
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def _onb(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangents of a unit vector (Duff et al. 2017 construction)."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    s = np.array([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    t = np.array([b, sign + n[1] * n[1] * a, -n[1]])
    return s, t


def parse_transform(node: Node) -> np.ndarray:
    m = np.eye(4)
    for c in node.children:
        what = f"<{c.tag}> in <transform name=\"{node.get('name')}\">"
        if c.tag == "translate":
            _check_attrs(c, {"x", "y", "z", "value"})
            op = translate(_vec3_attr(c, what, 0.0))
        elif c.tag == "scale":
            _check_attrs(c, {"x", "y", "z", "value"})
            op = scale(_vec3_attr(c, what, 1.0))
        elif c.tag == "rotate":
            _check_attrs(c, {"x", "y", "z", "value", "angle"})
            axis = _vec3_attr(c, what, 0.0)
            if "value" in c.attrib and len(_numbers(c, c.attrib["value"], what)) != 3:
                raise c.error(f"{what}: the rotation axis needs 3 numbers")
            if not np.linalg.norm(axis) > 0:
                raise c.error(f"{what}: rotation axis is zero")
            if "angle" not in c.attrib:
                raise c.error(f"{what}: missing 'angle'")
            op = rotate(axis, _float(c, c.attrib["angle"], what))
        elif c.tag == "matrix":
            _check_attrs(c, {"value"})
            v = _numbers(c, c.attrib.get("value", ""), what)
            if len(v) == 16:
                op = np.array(v).reshape(4, 4)
            elif len(v) == 9:
                op = np.eye(4)
                op[:3, :3] = np.array(v).reshape(3, 3)
            else:
                raise c.error(f"{what}: expected 16 (or 9) numbers, got {len(v)}")
        elif c.tag == "lookat":
            _check_attrs(c, {"origin", "target", "up"})
            vals = {}
            for k in ("origin", "target", "up"):
                if k not in c.attrib:
                    if k == "up":
                        continue
                    raise c.error(f"{what}: missing '{k}'")
                v = _numbers(c, c.attrib[k], f"{what} {k}")
                if len(v) != 3:
                    raise c.error(f"{what}: '{k}' needs 3 numbers")
                vals[k] = np.array(v)
            if "up" not in vals:
                d = vals["target"] - vals["origin"]
                dn = np.linalg.norm(d)
                vals["up"] = _onb(d / dn)[1] if dn > 0 else np.array([0.0, 1.0, 0.0])
            op = lookat(vals["origin"], vals["target"], vals["up"])
            if op is None:
                raise c.error(f"{what}: degenerate look-at (origin equals target, or 'up' is "
                              "parallel to the viewing direction)")
        else:
            raise c.error(f"unknown transform operation <{c.tag}> (supported: translate, rotate, "
                          "scale, matrix, lookat)")
        m = op @ m
    if not np.all(np.isfinite(m)):
        raise node.error("transform has non-finite entries")
    return m


# ---------------------------------------------------------------------------
# Property access with bookkeeping of what a plugin accepts

class Props:
    def __init__(self, loader: _Loader, node: Node):
        self.loader = loader
        self.node = node
        self.props: dict[str, Node] = {}
        self.named: dict[str, Node] = {}                   # name -> object node (resolved refs)
        self.unnamed: list[tuple[Node, Node]] = []         # (object node, element that placed it)
        self.used: set[str] = set()
        self.asked: set[str] = set()
        self.used_unnamed: set[int] = set()
        for c in node.children:
            name = c.get("name")
            if c.tag == "ref":
                _check_attrs(c, {"id", "name"})
                target = loader.resolve_ref(c)
                if name is not None and target.tag in ("texture", "spectrum", "rgb"):
                    self._add_named(name, target, c)
                else:
                    self.unnamed.append((target, c))
            elif c.tag in ("spectrum", "rgb", "texture") and "type" in c.attrib:
                if name is None:
                    if c.tag == "texture":
                        self.unnamed.append((c, c))
                        continue
                    raise c.error(f"<{c.tag} type=...> needs a 'name'")
                self._add_named(name, c, c)
            elif c.tag in PROPERTY_TAGS:
                if name is None:
                    raise c.error(f"<{c.tag}> needs a 'name' attribute")
                if name in self.props or name in self.named:
                    raise c.error(f"parameter '{name}' is given twice")
                self.props[name] = c
            elif c.tag in OBJECT_TAGS:
                if name is not None and c.tag == "texture":
                    self._add_named(name, c, c)
                else:
                    self.unnamed.append((c, c))
            elif c.tag in ("default", "include"):
                raise c.error(f"<{c.tag}> is only allowed at the top level of a scene")
            else:
                raise c.error(f"unknown element <{c.tag}> inside {node.describe()}")

    def _add_named(self, name: str, target: Node, where: Node) -> None:
        if name in self.props or name in self.named:
            raise where.error(f"parameter '{name}' is given twice")
        self.named[name] = target
        self.props[name] = where

    # -- generic
    def has(self, name: str) -> bool:
        self.asked.add(name)
        return name in self.props

    def _take(self, name: str, tags: tuple[str, ...], kind: str) -> Node | None:
        self.asked.add(name)
        p = self.props.get(name)
        if p is None:
            return None
        self.used.add(name)
        if name in self.named or p.tag not in tags:
            raise p.error(f"parameter '{name}' of {self.node.describe()} must be {kind}, "
                          f"not <{p.tag}>")
        _check_attrs(p, {"name", "value"} if p.tag not in ("point", "vector", "transform")
                     else {"name", "value", "x", "y", "z"})
        return p

    def float(self, name: str, default: float | None) -> float | None:
        p = self._take(name, ("float", "integer"), "a <float>")
        return default if p is None else _float(p, p.get("value"), f"parameter '{name}'")

    def int(self, name: str, default: int | None) -> int | None:
        p = self._take(name, ("integer",), "an <integer>")
        return default if p is None else _int(p, p.get("value"), f"parameter '{name}'")

    def bool(self, name: str, default: bool | None) -> bool | None:
        p = self._take(name, ("boolean",), "a <boolean>")
        return default if p is None else _bool(p, p.get("value"), f"parameter '{name}'")

    def string(self, name: str, default: str | None, choices: tuple | None = None) -> str | None:
        p = self._take(name, ("string",), "a <string>")
        if p is None:
            return default
        v = p.get("value")
        if v is None:
            raise p.error(f"parameter '{name}': missing 'value' attribute")
        if choices is not None and v not in choices:
            raise p.error(f"parameter '{name}' is '{v}', expected one of: {', '.join(choices)}")
        return v

    def point(self, name: str, default) -> np.ndarray | None:
        p = self._take(name, ("point", "vector"), "a <point> or <vector>")
        if p is None:
            return None if default is None else np.asarray(default, dtype=np.float64)
        return _finite(p, _vec3_attr(p, f"parameter '{name}'", 0.0), f"parameter '{name}'")

    def transform(self, name: str) -> np.ndarray | None:
        p = self._take(name, ("transform",), "a <transform>")
        return None if p is None else parse_transform(p)

    def color(self, name: str, default) -> np.ndarray | None:
        """A constant spectrum as linear RGB."""
        self.asked.add(name)
        if name in self.named:
            self.used.add(name)
            p = self.props[name]
            raise p.error(f"parameter '{name}' of {self.node.describe()} must be a constant "
                          "colour here, not a texture")
        p = self._take(name, ("float", "integer", "rgb", "srgb", "spectrum"),
                       "a colour (<rgb>, <spectrum> or <float>)")
        if p is None:
            return None if default is None else np.broadcast_to(
                np.asarray(default, dtype=np.float64), (3,)).copy()
        return self.loader.parse_color(p, f"parameter '{name}'")

    def texture(self, name: str, default, raw: bool = False) -> TextureDesc:
        self.asked.add(name)
        if name in self.named:
            self.used.add(name)
            tnode = self.named[name]
            if tnode.tag not in ("texture", "spectrum", "rgb"):
                raise self.props[name].error(
                    f"parameter '{name}' of {self.node.describe()} must be a texture or colour, "
                    f"not <{tnode.tag}>")
            return self.loader.build_texture(tnode, raw=raw)
        c = self.color(name, default)
        t = TextureDesc.constant(c)
        if name in self.props:
            t.source = self.loader.pos(self.props[name])
        return t

    def objects(self, tag: str) -> list[tuple[Node, Node]]:
        out = []
        for i, (obj, where) in enumerate(self.unnamed):
            if obj.tag == tag:
                self.used_unnamed.add(i)
                out.append((obj, where))
        return out

    def named_object(self, name: str, tag: str) -> Node | None:
        self.asked.add(name)
        if name not in self.props:
            return None
        self.used.add(name)
        obj = self.named.get(name)
        if obj is None or obj.tag != tag:
            raise self.props[name].error(f"parameter '{name}' must be a <{tag}>")
        return obj

    def ignore(self, *names: str) -> None:
        """Accepted-and-ignored parameters (type-checked only loosely)."""
        for n in names:
            self.asked.add(n)
            if n in self.props:
                self.used.add(n)

    def hints(self, names: tuple[str, ...]) -> set[str]:
        out = set()
        for n in names:
            if self.bool(n, False):
                out.add(n)
        return out

    def generic(self, name: str) -> Any:
        """Value of any property by its tag (for the papers' integrators)."""
        p = self.props[name]
        self.used.add(name)
        self.asked.add(name)
        if name in self.named:
            raise p.error(f"parameter '{name}' must be a plain value")
        what = f"parameter '{name}'"
        if p.tag == "integer":
            return _int(p, p.get("value"), what)
        if p.tag == "float":
            return _float(p, p.get("value"), what)
        if p.tag == "boolean":
            return _bool(p, p.get("value"), what)
        if p.tag == "string":
            v = p.get("value")
            if v is None:
                raise p.error(f"{what}: missing 'value' attribute")
            return v
        if p.tag in ("rgb", "srgb", "spectrum"):
            return self.loader.parse_color(p, what)
        if p.tag in ("point", "vector"):
            return _vec3_attr(p, what, 0.0)
        return parse_transform(p)

    def check(self) -> None:
        for name, p in self.props.items():
            if name not in self.used:
                sup = ", ".join(sorted(self.asked)) or "none"
                raise p.error(f"unknown parameter '{name}' for {self.node.describe()} "
                              f"(supported: {sup})")
        for i, (obj, where) in enumerate(self.unnamed):
            if i not in self.used_unnamed:
                raise where.error(f"unexpected {obj.describe()} inside {self.node.describe()}")


# ---------------------------------------------------------------------------

class _Loader:
    def __init__(self, base_dir: str, substitute: bool, params: dict[str, Any]):
        self.base_dir = base_dir
        self.substitute = substitute
        self.overrides = {k: self._param_str(v) for k, v in params.items()}
        self.vars: dict[str, str] = dict(self.overrides)
        self.ids: dict[str, Node] = {}
        self.warnings: list[str] = []
        self.include_stack: list[str] = []
        self.cache: dict[tuple[int, bool], Any] = {}
        self.building: set[int] = set()

    @staticmethod
    def _param_str(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (list, tuple, np.ndarray)):
            return ", ".join(str(x) for x in v)
        return str(v)

    def warn(self, node: Node | None, msg: str) -> None:
        self.warnings.append(f"{node.file}:{node.line}: {msg}" if node is not None else msg)

    def pos(self, node: Node) -> SourcePos:
        return SourcePos(node.file, node.line)

    def resolve_path(self, node: Node, filename: str) -> str:
        if os.path.isabs(filename):
            return filename
        cands = []
        if node.file and not node.file.startswith("<"):
            cands.append(os.path.join(os.path.dirname(os.path.abspath(node.file)), filename))
        cands.append(os.path.join(self.base_dir, filename))
        for c in cands:
            if os.path.exists(c):
                return c
        return cands[0]

    # -- phase 1 ------------------------------------------------------------
    def check_root(self, root: Node) -> None:
        if root.tag != "scene":
            raise root.error(f"the root element must be <scene>, not <{root.tag}>")
        _check_attrs(root, {"version"})
        v = root.get("version")
        if v is None:
            self.warn(root, "<scene> has no 'version' attribute; assuming Mitsuba 3 syntax")
            return
        try:
            major = int(v.strip().split(".")[0])
        except ValueError:
            raise root.error(f"bad scene version '{v}'") from None
        if major < 2:
            raise root.error(f"scene version {v} is the Mitsuba 0.x format, which is not "
                             "supported; write it as version 2.x or 3.x (Mitsuba 2 ships an "
                             "upgrade tool)")
        if major > 3:
            raise root.error(f"scene version {v} is not supported (2.x and 3.x are)")

    def substitute_attrs(self, node: Node) -> None:
        for k, v in node.attrib.items():
            if "$" in v:
                def rep(m: re.Match) -> str:
                    name = m.group(1)
                    if name not in self.vars:
                        raise node.error(f"parameter '${name}' is not defined (add a <default "
                                         f"name=\"{name}\" value=...> or pass {name}=...)")
                    return self.vars[name]
                node.attrib[k] = _VAR.sub(rep, v)

    def expand(self, nodes: list[Node], top: bool) -> list[Node]:
        out: list[Node] = []
        for n in nodes:
            if n.tag == "default":
                _check_attrs(n, {"name", "value"})
                self.substitute_attrs(n)
                name, value = n.get("name"), n.get("value")
                if not name or value is None:
                    raise n.error("<default> needs 'name' and 'value'")
                if name not in self.overrides:
                    self.vars[name] = value
                continue
            if n.tag == "include":
                self.substitute_attrs(n)
                _check_attrs(n, {"filename"})
                fn = n.get("filename")
                if not fn:
                    raise n.error("<include> needs a 'filename'")
                path = os.path.abspath(self.resolve_path(n, fn))
                if path in self.include_stack:
                    raise n.error(f"include cycle: '{fn}' includes itself (through "
                                  f"{' -> '.join(os.path.basename(p) for p in self.include_stack)})")
                try:
                    with open(path, "rb") as f:
                        data = f.read()
                except OSError:
                    raise n.error(f"included file '{fn}' not found (looked at {path})") from None
                sub = parse_xml(data, path)
                self.check_root(sub)
                self.include_stack.append(path)
                out.extend(self.expand(sub.children, top))
                self.include_stack.pop()
                continue
            self.substitute_attrs(n)
            n.children = self.expand(n.children, False)
            i = n.get("id")
            if i is not None and n.tag in OBJECT_TAGS:
                if i in self.ids:
                    o = self.ids[i]
                    raise n.error(f"id '{i}' is already used at {o.file}:{o.line}")
                self.ids[i] = n
            out.append(n)
        return out

    def resolve_ref(self, ref: Node) -> Node:
        i = ref.get("id")
        if i is None:
            raise ref.error("<ref> needs an 'id'")
        n = self.ids.get(i)
        if n is None:
            raise ref.error(f"reference to unknown id '{i}'")
        return n

    # -- colours --------------------------------------------------------------
    def parse_color(self, p: Node, what: str) -> np.ndarray:
        if p.tag == "spectrum" and "filename" in p.attrib:
            raise p.error(f"{what}: spectra from files are not supported; give "
                          "'wavelength:value' pairs or an <rgb>")
        v = p.get("value")
        if v is None:
            raise p.error(f"{what}: missing 'value' attribute")
        if p.tag in ("float", "integer"):
            return np.full(3, _float(p, v, what))
        if p.tag == "srgb":
            s = v.strip()
            if s.startswith("#"):
                try:
                    h = s[1:]
                    if len(h) != 6:
                        raise ValueError
                    c = np.array([int(h[i:i + 2], 16) for i in (0, 2, 4)]) / 255.0
                except ValueError:
                    raise p.error(f"{what}: bad hex colour '{v}'") from None
            else:
                c = np.array(_numbers(p, v, what))
            if len(c) == 1:
                c = np.repeat(c, 3)
            if len(c) != 3:
                raise p.error(f"{what}: expected 1 or 3 numbers")
            return _finite(p, spectra.srgb_to_linear(c), what)
        if p.tag == "rgb":
            c = _numbers(p, v, what)
            if len(c) == 1:
                c = c * 3
            if len(c) != 3:
                raise p.error(f"{what}: <rgb> expects 1 or 3 numbers, got {len(c)}")
            return _finite(p, np.array(c), what)
        # spectrum
        if ":" in v:
            wl, val = [], []
            for item in v.split(","):
                item = item.strip()
                if not item:
                    continue
                ab = item.split(":")
                if len(ab) != 2:
                    raise p.error(f"{what}: expected 'wavelength:value' pairs, got '{item}'")
                a, b = _float(p, ab[0], what), _float(p, ab[1], what)
                wl.append(a)
                val.append(b)
            if not wl:
                raise p.error(f"{what}: empty spectrum")
            if not all(np.isfinite(wl)) or not all(np.isfinite(val)):
                raise p.error(f"{what}: spectrum values must be finite")
            if len(set(wl)) != len(wl):
                raise p.error(f"{what}: repeated wavelength in spectrum")
            return spectra.spectrum_to_rgb(wl, val)
        c = _numbers(p, v, what)
        if len(c) == 1:
            return _finite(p, np.full(3, c[0]), what)
        if len(c) == 3:
            self.warn(p, f"{what}: a 3-value <spectrum> is read as RGB")
            return _finite(p, np.array(c), what)
        raise p.error(f"{what}: a <spectrum> needs one value or 'wavelength:value' pairs")

    # -- textures -------------------------------------------------------------
    def build_texture(self, node: Node, raw: bool = False) -> TextureDesc:
        key = (id(node), raw)
        if key in self.cache:
            return self.cache[key]
        t = node.get("type")
        _check_attrs(node, {"type", "name", "id"})
        p = Props(self, node)
        if t == "bitmap":
            fn = p.string("filename", None)
            if fn is None:
                raise node.error("bitmap texture needs a 'filename'")
            filt = p.string("filter_type", "bilinear", ("bilinear", "nearest"))
            wrap = p.string("wrap_mode", "repeat", ("repeat", "mirror", "clamp"))
            is_raw = p.bool("raw", False)
            to_uv = p.transform("to_uv")
            p.ignore("format", "accel")
            p.check()
            if raw and not is_raw:
                self.warn(node, "normal map texture read with raw=true (no sRGB decoding)")
            tex = self._bitmap(p.props["filename"], fn, raw or is_raw, normal=raw)
            tex.filter, tex.wrap = filt, wrap
            tex.to_uv = self._uv3(to_uv)
        elif t == "checkerboard":
            c0 = p.color("color0", 0.4)
            c1 = p.color("color1", 0.2)
            to_uv = p.transform("to_uv")
            p.check()
            tex = TextureDesc(kind="checkerboard", color0=c0, color1=c1, to_uv=self._uv3(to_uv))
        else:
            raise node.error(f"unsupported texture type '{t}' (supported: {', '.join(TEXTURE_TYPES)})")
        tex.source = self.pos(node)
        self.cache[key] = tex
        return tex

    @staticmethod
    def _uv3(m: np.ndarray | None) -> np.ndarray:
        if m is None:
            return np.eye(3)
        return m[np.ix_([0, 1, 3], [0, 1, 3])].copy()

    def _bitmap(self, where: Node, fn: str, raw: bool, normal: bool = False) -> TextureDesc:
        path = self.resolve_path(where, fn)
        if not os.path.isfile(path):
            if not self.substitute:
                raise where.error(f"texture file '{fn}' not found (looked at {path}); pass "
                                  "substitute_missing_textures=True to render with a stand-in")
            if normal:
                self.warn(where, f"texture '{fn}' is missing: using a flat normal map")
                img = np.array([[[0.5, 0.5, 1.0]]], dtype=np.float32)
                return TextureDesc(kind="bitmap", image=img)
            self.warn(where, f"texture '{fn}' is missing: using constant mid-grey 0.5")
            return TextureDesc.constant(0.5)
        try:
            img = read_image(path, raw=raw)
        except SceneError as e:
            raise where.error(f"texture '{fn}': {e.problem}") from None
        return TextureDesc(kind="bitmap", image=img)

    # -- BSDFs ----------------------------------------------------------------
    def build_bsdf(self, node: Node) -> BSDFDesc:
        key = (id(node), False)
        if key in self.cache:
            return self.cache[key]
        if id(node) in self.building:
            raise node.error("BSDF refers to itself")
        self.building.add(id(node))
        try:
            b = self._build_bsdf(node)
        finally:
            self.building.discard(id(node))
        b.id = node.get("id")
        b.source = self.pos(node)
        self.cache[key] = b
        return b

    def _ior(self, p: Props, name: str, default: str) -> float:
        pn = p.props.get(name)
        if pn is not None and pn.tag == "string" and name not in p.named:
            s = p.string(name, None)
            v = spectra.lookup_ior(s)
            if v is None:
                raise pn.error(f"unknown IOR name '{s}' (known: {', '.join(spectra.IOR_TABLE)})")
            return v
        v = p.float(name, None)
        if v is None:
            return spectra.IOR_TABLE[default]
        if not (v > 0 and math.isfinite(v)):
            raise pn.error(f"parameter '{name}' must be a positive number")
        return v

    def _alpha(self, p: Props, node: Node, aniso_ok: bool) -> tuple[float, float]:
        a = p.float("alpha", None)
        au = p.float("alpha_u", None)
        av = p.float("alpha_v", None)
        if a is not None and (au is not None or av is not None):
            raise node.error("give either 'alpha' or 'alpha_u'/'alpha_v', not both")
        if (au is None) != (av is None):
            raise node.error("'alpha_u' and 'alpha_v' must be given together")
        if au is None:
            au = av = 0.1 if a is None else a
        for v in (au, av):
            if not (v >= 0 and math.isfinite(v)):
                raise node.error("roughness alpha must be a finite number >= 0")
        if not aniso_ok and au != av:
            raise node.error("anisotropic roughness (alpha_u != alpha_v) is not supported for "
                             "this BSDF")
        return au, av

    def _build_bsdf(self, node: Node) -> BSDFDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        p = Props(self, node)
        params: dict[str, Any] = {}
        if t == "diffuse":
            params["reflectance"] = p.texture("reflectance", 0.5)
        elif t in ("conductor", "roughconductor"):
            mat = p.string("material", None)
            eta = p.color("eta", None)
            k = p.color("k", None)
            if eta is None and k is None:
                mname = mat if mat is not None else "none"
                ek = spectra.lookup_conductor(mname)
                if ek is None:
                    raise p.props["material"].error(
                        f"unknown conductor material '{mname}' (known: "
                        f"{', '.join(spectra.CONDUCTORS)}; or give 'eta' and 'k')")
                eta, k = ek
            elif eta is None or k is None:
                raise node.error("conductor: give both 'eta' and 'k' (or a 'material')")
            elif mat is not None:
                raise node.error("conductor: give either 'material' or 'eta'/'k', not both")
            params["eta"], params["k"] = eta, k
            params["specular_reflectance"] = p.texture("specular_reflectance", 1.0)
            if t == "roughconductor":
                params["alpha_u"], params["alpha_v"] = self._alpha(p, node, True)
                params["distribution"] = p.string("distribution", "beckmann", ("beckmann", "ggx"))
                params["sample_visible"] = p.bool("sample_visible", True)
        elif t in ("dielectric", "thindielectric", "roughdielectric"):
            params["int_ior"] = self._ior(p, "int_ior", "bk7")
            params["ext_ior"] = self._ior(p, "ext_ior", "air")
            params["specular_reflectance"] = p.texture("specular_reflectance", 1.0)
            params["specular_transmittance"] = p.texture("specular_transmittance", 1.0)
            if t == "roughdielectric":
                params["alpha"] = self._alpha(p, node, False)[0]
                params["distribution"] = p.string("distribution", "beckmann", ("beckmann", "ggx"))
                params["sample_visible"] = p.bool("sample_visible", True)
        elif t in ("plastic", "roughplastic"):
            params["diffuse_reflectance"] = p.texture("diffuse_reflectance", 0.5)
            params["specular_reflectance"] = p.texture("specular_reflectance", 1.0)
            params["int_ior"] = self._ior(p, "int_ior", "polypropylene")
            params["ext_ior"] = self._ior(p, "ext_ior", "air")
            params["nonlinear"] = p.bool("nonlinear", False)
            if t == "roughplastic":
                params["alpha"] = self._alpha(p, node, False)[0]
                params["distribution"] = p.string("distribution", "beckmann", ("beckmann", "ggx"))
                p.ignore("sample_visible")
                self.warn(node, "roughplastic is rendered as smooth plastic (its alpha and "
                          "distribution are kept in the BSDF's params)")
                t = "plastic"
        elif t == "twosided":
            kids = p.objects("bsdf")
            if len(kids) not in (1, 2):
                raise node.error(f"twosided needs one or two nested BSDFs, got {len(kids)}")
            front = self.build_bsdf(kids[0][0])
            params["front"] = front
            params["back"] = self.build_bsdf(kids[1][0]) if len(kids) == 2 else front
        elif t == "normalmap":
            kids = p.objects("bsdf")
            if len(kids) != 1:
                raise node.error(f"normalmap needs exactly one nested BSDF, got {len(kids)}")
            params["nested"] = self.build_bsdf(kids[0][0])
            tnode = p.named_object("normalmap", "texture")
            fn = p.string("filename", None)
            tiles = p.float("tiles", None)
            use_slopes = p.bool("use_slopes", None)
            if tnode is not None and fn is not None:
                raise node.error("normalmap: give either a 'normalmap' texture or a 'filename'")
            if tnode is not None:
                tex = self.build_texture(tnode, raw=True)
            elif fn is not None:
                tex = self._bitmap(p.props["filename"], fn, raw=True, normal=True)
            else:
                raise node.error("normalmap needs a <texture name=\"normalmap\" type=\"bitmap\"> "
                                 "or a <string name=\"filename\">")
            if tex.kind == "constant":
                raise node.error("normalmap: the normal map must be a bitmap texture")
            if tiles is not None:
                if not (tiles > 0 and math.isfinite(tiles)):
                    raise p.props["tiles"].error("normalmap 'tiles' must be positive")
                tex = TextureDesc(kind=tex.kind, image=tex.image, to_uv=np.diag([tiles, tiles, 1.0])
                                  @ tex.to_uv, filter=tex.filter, wrap=tex.wrap, source=tex.source)
            params["normalmap"] = tex
            if use_slopes is not None:
                params["use_slopes"] = use_slopes
        elif t == "null":
            pass
        else:
            raise node.error(f"unsupported BSDF type '{t}' (supported: {', '.join(BSDF_TYPES)})")
        p.check()
        return BSDFDesc(type=t, params=params)

    # -- emitters -------------------------------------------------------------
    def build_emitter(self, node: Node, attached: bool) -> EmitterDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t not in EMITTER_TYPES:
            raise node.error(f"unsupported emitter type '{t}' (supported: {', '.join(EMITTER_TYPES)})")
        if t == "area" and not attached:
            raise node.error("an area emitter must be nested inside a <shape>")
        if t != "area" and attached:
            raise node.error(f"a '{t}' emitter cannot be attached to a shape (only 'area')")
        p = Props(self, node)
        params: dict[str, Any] = {}

        def nonneg(name: str, default) -> np.ndarray:
            c = p.color(name, default)
            if np.any(c < 0) or not np.all(np.isfinite(c)):
                raise p.props[name].error(f"emitter '{name}' must be finite and non-negative")
            return c

        if t == "area":
            params["radiance"] = nonneg("radiance", 1.0)
        elif t == "point":
            params["intensity"] = nonneg("intensity", 1.0)
            pos = p.point("position", None)
            m = p.transform("to_world")
            if pos is not None and m is not None:
                raise node.error("point emitter: give either 'position' or 'to_world'")
            params["position"] = pos if pos is not None else (m[:3, 3].copy() if m is not None
                                                               else np.zeros(3))
        elif t == "spot":
            params["intensity"] = nonneg("intensity", 1.0)
            cutoff = p.float("cutoff_angle", 20.0)
            beam = p.float("beam_width", None)
            if not (0 < cutoff <= 180):
                raise node.error("spot emitter: cutoff_angle must be in (0, 180] degrees")
            if beam is None:
                beam = cutoff * 0.75
            if not (0 < beam):
                raise node.error("spot emitter: beam_width must be positive")
            if beam > cutoff:
                self.warn(node, "spot emitter: beam_width larger than cutoff_angle; clamped")
                beam = cutoff
            m = p.transform("to_world")
            params.update(cutoff_angle=cutoff, beam_width=beam,
                          to_world=m if m is not None else np.eye(4))
            p.ignore("texture")
            if "texture" in p.props:
                raise p.props["texture"].error("spot emitter textures are not supported")
        elif t == "directional":
            params["irradiance"] = nonneg("irradiance", 1.0)
            d = p.point("direction", None)
            m = p.transform("to_world")
            if d is not None and m is not None:
                raise node.error("directional emitter: give either 'direction' or 'to_world'")
            if d is None:
                d = (m[:3, :3] @ np.array([0.0, 0.0, 1.0])) if m is not None else np.array([0.0, 0, 1])
            n = np.linalg.norm(d)
            if not n > 0:
                raise node.error("directional emitter: direction is zero")
            params["direction"] = d / n
        elif t == "constant":
            params["radiance"] = nonneg("radiance", 1.0)
        elif t == "envmap":
            fn = p.string("filename", None)
            if fn is None:
                raise node.error("envmap needs a 'filename'")
            sc = p.float("scale", 1.0)
            if not (sc >= 0 and math.isfinite(sc)):
                raise p.props["scale"].error("envmap 'scale' must be finite and >= 0")
            m = p.transform("to_world")
            where = p.props["filename"]
            path = self.resolve_path(where, fn)
            if not os.path.isfile(path):
                if not self.substitute:
                    raise where.error(f"environment map '{fn}' not found (looked at {path}); pass "
                                      "substitute_missing_textures=True to use a stand-in")
                self.warn(where, f"environment map '{fn}' is missing: using constant mid-grey 0.5")
                img = np.full((2, 4, 3), 0.5, dtype=np.float32)
            else:
                try:
                    img = read_image(path)
                except SceneError as e:
                    raise where.error(f"environment map '{fn}': {e.problem}") from None
            if np.any(img < 0):
                raise where.error(f"environment map '{fn}' has negative values")
            p.ignore("mis_compensation")
            params.update(image=img, scale=sc, to_world=m if m is not None else np.eye(4))
        hints = p.hints(EMITTER_HINTS)
        p.check()
        return EmitterDesc(type=t, params=params, hints=hints, source=self.pos(node))

    # -- shapes ---------------------------------------------------------------
    def build_shape(self, node: Node) -> ShapeDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t not in SHAPE_TYPES:
            raise node.error(f"unsupported shape type '{t}' (supported: {', '.join(SHAPE_TYPES)})")
        p = Props(self, node)
        m = p.transform("to_world")
        if m is None:
            m = np.eye(4)
        flip = p.bool("flip_normals", False)
        hints = p.hints(SHAPE_HINTS)
        bs = p.objects("bsdf")
        if len(bs) > 1:
            raise bs[1][1].error("a shape can have only one BSDF")
        bsdf = self.build_bsdf(bs[0][0]) if bs else BSDFDesc(
            type="diffuse", params={"reflectance": TextureDesc.constant(0.5)})
        es = p.objects("emitter")
        if len(es) > 1:
            raise es[1][1].error("a shape can have only one emitter")
        emitter = self.build_emitter(es[0][0], attached=True) if es else None
        for obj, where in p.unnamed:
            if obj.tag in ("medium", "shape", "sensor"):
                raise where.error(f"{obj.describe()} inside a shape is not supported")
        sd = ShapeDesc(kind="mesh", bsdf=bsdf, flip_normals=flip, emitter=emitter, hints=hints,
                       id=node.get("id"), source=self.pos(node))

        if t == "sphere":
            center = p.point("center", (0.0, 0.0, 0.0))
            radius = p.float("radius", 1.0)
            p.check()
            if not (radius > 0 and math.isfinite(radius)):
                raise node.error("sphere radius must be positive")
            a = m[:3, :3]
            g = a.T @ a
            s2 = np.trace(g) / 3.0
            if not s2 > 0 or np.max(np.abs(g - s2 * np.eye(3))) > 1e-5 * s2:
                raise node.error("sphere to_world must be a similarity (rotation, uniform scale, "
                                 "translation); non-uniform scale or shear is not supported")
            sd.kind = "sphere"
            sd.center = (m @ np.append(center, 1.0))[:3]
            sd.radius = float(radius * math.sqrt(s2))
            if not (np.all(np.isfinite(sd.center)) and math.isfinite(sd.radius)):
                raise node.error("sphere center or radius is not finite after to_world")
            if emitter is not None and not sd.radius > 0:
                raise node.error("area emitter on a shape of zero area")
            return sd

        face_normals = False
        if t in ("obj", "ply", "serialized"):
            fn = p.string("filename", None)
            if fn is None:
                raise node.error(f"'{t}' shape needs a 'filename'")
            face_normals = p.bool("face_normals", False)
            flip_tc = p.bool("flip_tex_coords", True) if t in ("obj", "serialized") else False
            shape_index = p.int("shape_index", 0) if t == "serialized" else 0
            p.check()
            where = p.props["filename"]
            path = self.resolve_path(where, fn)
            if not os.path.isfile(path):
                if not self.substitute:
                    raise where.error(f"mesh file '{fn}' not found (looked at {path}); pass "
                                      "substitute_missing_textures=True to use a stand-in")
                self.warn(where, f"mesh '{fn}' is missing: using a small flat stand-in")
                mesh = shp.stand_in()
            else:
                try:
                    if t == "obj":
                        mesh = shp.read_obj(path, flip_tc)
                    elif t == "ply":
                        mesh = shp.read_ply(path)
                    else:
                        mesh = shp.read_serialized(path, shape_index, flip_tc)
                except OSError as e:
                    raise where.error(f"could not read mesh '{fn}': {e}") from None
                except SceneError as e:
                    loc = f"{fn}:{e.line}" if e.line is not None else fn
                    raise SceneError(f"mesh {loc}: {e.problem}", where.file, where.line) from None
                if mesh.normals_partial:
                    self.warn(where, f"mesh '{fn}': only some faces have normals; normals are "
                              "recomputed")
        elif t == "rectangle":
            p.check()
            mesh = shp.rectangle()
        elif t == "disk":
            p.check()
            mesh = shp.disk()
        elif t == "cube":
            p.check()
            mesh = shp.cube()
        elif t == "cylinder":
            p0 = p.point("p0", (0.0, 0.0, 0.0))
            p1 = p.point("p1", (0.0, 0.0, 1.0))
            r = p.float("radius", 1.0)
            p.check()
            if not (r > 0 and math.isfinite(r)):
                raise node.error("cylinder radius must be positive")
            d = p1 - p0
            length = np.linalg.norm(d)
            if not length > 0:
                raise node.error("cylinder p0 and p1 coincide")
            s, tt = _onb(d / length)
            frame = np.eye(4)
            frame[:3, 0], frame[:3, 1], frame[:3, 2] = s, tt, d / length
            m = m @ translate(p0) @ frame @ scale([r, r, length])
            mesh = shp.cylinder()
        else:  # pragma: no cover - guarded above
            raise node.error(f"unsupported shape type '{t}'")
        src = p.props.get("filename", node)
        return self._finish_mesh(sd, mesh, m, face_normals, node, src)

    def _finish_mesh(self, sd: ShapeDesc, mesh: shp.Mesh, m: np.ndarray, face_normals: bool,
                     node: Node, src: Node) -> ShapeDesc:
        """Validate, transform and convert a mesh; `src` is the element naming its file."""
        fname = src.get("value", "") if src is not node else ""
        what = f"mesh '{fname}'" if fname else "mesh"
        if mesh.positions.shape[0] == 0 or mesh.indices.shape[0] == 0:
            raise src.error(f"{what} is empty")
        if not np.all(np.isfinite(mesh.positions)):
            raise src.error(f"{what} contains NaN or infinite vertex positions")
        if mesh.indices.min() < 0 or mesh.indices.max() >= len(mesh.positions):
            raise src.error(f"{what}: face index out of range (the mesh has "
                            f"{len(mesh.positions)} vertices)")
        if mesh.uvs is not None and not np.all(np.isfinite(mesh.uvs)):
            raise src.error(f"{what} contains NaN or infinite texture coordinates")
        mesh = shp.transform_mesh(mesh, m)
        if not np.all(np.isfinite(mesh.positions)):
            raise node.error("mesh positions are not finite after to_world")
        normals = None
        if not face_normals:
            n = mesh.normals
            if n is None:
                n = shp.vertex_normals(mesh.positions, mesh.indices)
            n, bad = shp.normalize_rows(n)
            if bad.any() or not np.all(np.isfinite(n)):
                used = np.zeros(len(n), bool)
                used[mesh.indices.reshape(-1)] = True
                if (bad & used).any() or not np.all(np.isfinite(n[used])):
                    self.warn(node, f"mesh has {int((bad & used).sum())} zero-length or invalid "
                              "vertex normals: using face normals for the whole mesh")
                    n = None
                else:
                    n = np.where(bad[:, None], 0.0, n)
            normals = n
        with np.errstate(over="ignore"):
            sd.positions = mesh.positions.astype(np.float32)
        if not np.all(np.isfinite(sd.positions)):
            raise node.error("mesh positions overflow single precision after to_world")
        sd.indices = mesh.indices.astype(np.uint32)
        sd.normals = None if normals is None else normals.astype(np.float32)
        sd.uvs = None if mesh.uvs is None else mesh.uvs.astype(np.float32)
        if sd.emitter is not None and not shp.mesh_area(mesh.positions, mesh.indices) > 0:
            raise node.error("area emitter on a shape of zero area")
        return sd

    # -- sensor / film / sampler ---------------------------------------------
    def build_rfilter(self, node: Node) -> FilterDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        p = Props(self, node)
        if t == "box":
            f = FilterDesc("box")
        elif t == "gaussian":
            sd = p.float("stddev", 0.5)
            if not (sd > 0 and math.isfinite(sd)):
                raise node.error("gaussian filter stddev must be positive")
            f = FilterDesc("gaussian", stddev=sd)
        elif t == "tent":
            r = p.float("radius", 1.0)
            if not (r > 0 and math.isfinite(r)):
                raise node.error("tent filter radius must be positive")
            f = FilterDesc("tent", radius=r)
        else:
            raise node.error(f"unsupported reconstruction filter '{t}' (supported: box, gaussian, "
                             "tent)")
        p.check()
        return f

    def build_film(self, node: Node, cam: CameraDesc) -> None:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t != "hdrfilm":
            raise node.error(f"unsupported film type '{t}' (supported: hdrfilm)")
        p = Props(self, node)
        w = p.int("width", 768)
        h = p.int("height", 576)
        if not (0 < w <= 1 << 16 and 0 < h <= 1 << 16):
            raise node.error(f"film size {w}x{h} is invalid (1..65536)")
        ox = p.int("crop_offset_x", 0)
        oy = p.int("crop_offset_y", 0)
        cw = p.int("crop_width", w)
        ch = p.int("crop_height", h)
        if ox < 0 or oy < 0 or cw <= 0 or ch <= 0 or ox + cw > w or oy + ch > h:
            raise node.error(f"crop window offset ({ox}, {oy}) size ({cw}, {ch}) does not fit the "
                             f"{w}x{h} film")
        p.ignore("pixel_format", "component_format", "file_format", "banner",
                 "high_quality_edges", "sample_border", "compensate", "srgb")
        rf = p.objects("rfilter")
        if len(rf) > 1:
            raise rf[1][1].error("only one rfilter per film")
        cam.rfilter = self.build_rfilter(rf[0][0]) if rf else FilterDesc()
        p.check()
        cam.width, cam.height, cam.crop = w, h, (ox, oy, cw, ch)

    def build_sampler(self, node: Node, cam: CameraDesc) -> None:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t != "independent":
            if t not in SAMPLER_ALIASES:
                raise node.error(f"unsupported sampler '{t}' (supported: independent; "
                                 f"{', '.join(SAMPLER_ALIASES)}, which stratify the pixel "
                                 "positions)")
            cam.sampler = "stratified"
        p = Props(self, node)
        n = p.int("sample_count", 4)
        if not 0 < n < 1 << 40:
            raise node.error("sample_count must be positive")
        p.ignore("seed", "jitter", "strength", "scramble_seed", "dimension", "scramble")
        p.check()
        cam.spp = n

    def build_sensor(self, node: Node) -> CameraDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t != "perspective":
            raise node.error(f"unsupported sensor type '{t}' (supported: perspective; thinlens "
                             "and others are not implemented)")
        cam = CameraDesc(source=self.pos(node))
        p = Props(self, node)
        for obj, where in p.objects("film"):
            self.build_film(obj, cam)
        for obj, where in p.objects("sampler"):
            self.build_sampler(obj, cam)
        fov = p.float("fov", None)
        fl = p.props.get("focal_length")
        p.asked.add("focal_length")
        axis = p.string("fov_axis", "x", ("x", "y", "diagonal", "smaller", "larger"))
        if fl is not None:
            p.used.add("focal_length")
            if fov is not None:
                raise fl.error("give either 'fov' or 'focal_length', not both")
            if fl.tag not in ("string", "float"):
                raise fl.error("focal_length must be a <string> like \"50mm\" or a <float>")
            s = (fl.get("value") or "").strip()
            f = _float(fl, s.removesuffix("mm"), "focal_length")
            if not f > 0:
                raise fl.error("focal_length must be positive")
            fov = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / (2 * f)))
            axis = "diagonal"
        elif fov is None:
            fov = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / 100.0))   # 50 mm
            axis = "diagonal"
        if not (0 < fov < 180):
            where = p.props.get("fov", node)
            raise where.error(f"fov must be in (0, 180) degrees, got {fov}")
        near = p.float("near_clip", 1e-2)
        far = p.float("far_clip", 1e4)
        if not (0 < near < far):
            raise node.error(f"near_clip ({near}) and far_clip ({far}) must satisfy 0 < near < far")
        m = p.transform("to_world")
        for k in ("principal_point_offset_x", "principal_point_offset_y"):
            v = p.float(k, 0.0)
            if v != 0.0:
                raise p.props[k].error(f"'{k}' is not supported")
        p.ignore("shutter_open", "shutter_close", "srf")
        p.check()
        if m is not None:
            a = m[:3, :3]
            if not abs(np.linalg.det(a)) > 1e-12:
                raise node.error("sensor to_world is singular")
        cam.fov, cam.fov_axis, cam.near_clip, cam.far_clip = fov, axis, near, far
        cam.to_world = m if m is not None else np.eye(4)
        return cam

    # -- integrator -----------------------------------------------------------
    def build_integrator(self, node: Node) -> IntegratorDesc:
        t = node.get("type")
        _check_attrs(node, {"type", "id", "name"})
        if t not in INTEGRATOR_TYPES:
            raise node.error(f"unsupported integrator '{t}' (supported: "
                             f"{', '.join(INTEGRATOR_TYPES)})")
        p = Props(self, node)
        params: dict[str, Any] = {}

        def std() -> None:
            md = p.int("max_depth", -1)
            rr = p.int("rr_depth", 5)
            if md < -1:
                raise p.props["max_depth"].error("max_depth must be -1 (infinite) or >= 0")
            if rr < 1:
                raise p.props["rr_depth"].error("rr_depth must be >= 1")
            params.update(max_depth=md, rr_depth=rr, hide_emitters=p.bool("hide_emitters", False))

        out_type = t
        if t in ("path", "ptracer", "volpath"):
            std()
            for k in ("samples_per_pass", "timeout"):
                if p.has(k):
                    params[k] = p.generic(k)
            if t == "volpath":
                self.warn(node, "integrator 'volpath' is rendered with 'path' (no media)")
                out_type = "path"
        elif t == "direct":
            params.update(max_depth=2, rr_depth=5, hide_emitters=p.bool("hide_emitters", False))
            p.ignore("emitter_samples", "bsdf_samples", "shading_samples")
            self.warn(node, "integrator 'direct' is rendered with 'path' and max_depth=2")
            out_type = "path"
        else:  # the papers' integrators: keep every knob
            std()
            for name in list(p.props):
                if name in p.used:
                    continue
                params[name] = p.generic(name)
                if name not in PAPER_KNOBS:
                    self.warn(p.props[name], f"integrator '{t}': parameter '{name}' is not a "
                              "known knob; kept as given")
        p.check()
        return IntegratorDesc(type=out_type, params=params, source=self.pos(node))

    # -- scene ----------------------------------------------------------------
    def build_scene(self, root: Node, filename: str | None) -> SceneDesc:
        self.check_root(root)
        nodes = self.expand(root.children, True)
        scene = SceneDesc(filename=filename, warnings=self.warnings)
        camera = None
        integrator = None
        for n in nodes:
            if n.tag == "shape":
                scene.shapes.append(self.build_shape(n))
            elif n.tag == "emitter":
                scene.emitters.append(self.build_emitter(n, attached=False))
            elif n.tag == "sensor":
                if camera is not None:
                    self.warn(n, "more than one sensor: only the first one is used")
                    self.build_sensor(n)
                else:
                    camera = self.build_sensor(n)
            elif n.tag == "integrator":
                if integrator is not None:
                    raise n.error("more than one <integrator>")
                integrator = self.build_integrator(n)
            elif n.tag in ("bsdf", "texture"):
                if n.get("id") is None:
                    self.warn(n, f"top-level {n.describe()} without id is unused")
                if n.tag == "bsdf":
                    self.build_bsdf(n)
                else:
                    self.build_texture(n)
            elif n.tag in ("film", "sampler", "rfilter"):
                if n.get("id") is None:
                    raise n.error(f"a top-level <{n.tag}> needs an id and a <ref> from the sensor")
                tmp = CameraDesc()
                if n.tag == "film":
                    self.build_film(n, tmp)
                elif n.tag == "sampler":
                    self.build_sampler(n, tmp)
                else:
                    self.build_rfilter(n)
            elif n.tag in ("medium", "phase", "volume"):
                raise n.error(f"<{n.tag}> (participating media) is not supported")
            elif n.tag == "ref":
                raise n.error("<ref> at the top level of a scene has no effect; place it inside "
                              "a plugin")
            elif n.tag in PROPERTY_TAGS:
                raise n.error(f"<{n.tag}> property at the top level of a scene")
            else:
                raise n.error(f"unknown element <{n.tag}>")
        scene.integrator = integrator if integrator is not None else IntegratorDesc(
            type="path", params={"max_depth": -1, "rr_depth": 5, "hide_emitters": False})
        if camera is None:
            camera = self.default_camera(scene)
        scene.camera = camera
        return scene

    def default_camera(self, scene: SceneDesc) -> CameraDesc:
        """No sensor: a 45-degree camera on the +z side of the scene's bounding box,
        looking down -z with +y up, far enough to see the whole box."""
        cam = CameraDesc()
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for s in scene.shapes:
            if s.kind == "sphere":
                lo = np.minimum(lo, s.center - s.radius)
                hi = np.maximum(hi, s.center + s.radius)
            elif s.positions is not None:
                lo = np.minimum(lo, s.positions.min(axis=0))
                hi = np.maximum(hi, s.positions.max(axis=0))
        if not np.all(np.isfinite(lo)):
            lo, hi = np.full(3, -1.0), np.full(3, 1.0)
        c = 0.5 * (lo + hi)
        r = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        d = r / math.sin(math.radians(cam.fov) / 2) * 1.1
        cam.to_world = lookat(c + np.array([0.0, 0.0, d]), c, np.array([0.0, 1.0, 0.0]))
        cam.far_clip = max(cam.far_clip, 4 * d)
        cam.near_clip = min(cam.near_clip, d * 1e-3)
        self.warnings.append("the scene has no sensor: using a default 45-degree camera looking "
                             "down -z at the scene")
        return cam


# ---------------------------------------------------------------------------

def load_string(xml: str | bytes, base_dir: str | None = None,
                substitute_missing_textures: bool = False, *, source_name: str | None = None,
                **params: Any) -> SceneDesc:
    """Load a scene from XML text. Relative paths resolve against base_dir
    (default: the current directory). params override <default> values."""
    name = source_name or "<string>"
    ld = _Loader(os.path.abspath(base_dir or os.getcwd()), substitute_missing_textures, params)
    if source_name is not None:
        ld.include_stack.append(os.path.abspath(source_name))
    root = parse_xml(xml, name)
    return ld.build_scene(root, source_name)


def load_file(path: str | os.PathLike, substitute_missing_textures: bool = False,
              **params: Any) -> SceneDesc:
    """Load a Mitsuba 2/3 scene file. params override <default> values (like -D)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise SceneError(f"cannot read scene file: {e.strerror or e}", path) from None
    return load_string(data, os.path.dirname(os.path.abspath(path)),
                       substitute_missing_textures, source_name=path, **params)
