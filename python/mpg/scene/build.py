"""Hand a validated SceneDesc to the C++ core."""

from __future__ import annotations

from typing import Any

import numpy as np

from mpg.errors import SceneError
from mpg.scene.desc import BSDFDesc, SceneDesc, TextureDesc


def _core():
    from mpg import _core

    return _core


class _Builder:
    def __init__(self, desc: SceneDesc):
        self.desc = desc
        self.core = _core().Scene()
        self._tex: dict[int, int] = {}
        self._bsdf: dict[int, int] = {}

    def texture(self, t: TextureDesc | None) -> int:
        if t is None:
            return -1
        key = id(t)
        if key in self._tex:
            return self._tex[key]
        if t.kind == "constant":
            tid = self.core.add_texture_constant(np.asarray(t.value, dtype=np.float64).tolist())
        elif t.kind == "bitmap":
            img = np.ascontiguousarray(t.image, dtype=np.float32)
            if img.ndim == 2:
                img = np.repeat(img[:, :, None], 3, axis=2)
            tid = self.core.add_texture_bitmap(
                img[:, :, :3], np.asarray(t.to_uv, dtype=np.float64), t.filter != "nearest", t.wrap
            )
        elif t.kind == "checkerboard":
            tid = self.core.add_texture_checker(
                np.asarray(t.color0).tolist(), np.asarray(t.color1).tolist(),
                np.asarray(t.to_uv, dtype=np.float64),
            )
        else:
            raise SceneError(f"unsupported texture kind '{t.kind}'")
        self._tex[key] = tid
        return tid

    def bsdf(self, b: BSDFDesc) -> int:
        key = id(b)
        if key in self._bsdf:
            return self._bsdf[key]
        p: dict[str, Any] = {}
        for name, v in b.params.items():
            if isinstance(v, TextureDesc):
                p[name] = self.texture(v)
            elif isinstance(v, BSDFDesc):
                p[name] = self.bsdf(v)
            elif isinstance(v, np.ndarray):
                p[name] = v.astype(np.float64).tolist()
            else:
                p[name] = v
        if b.type == "diffuse" and "reflectance" not in p:
            p["reflectance"] = self.texture(TextureDesc.constant(0.5))
        if b.type == "plastic" and "diffuse_reflectance" in p:
            p["reflectance"] = p.pop("diffuse_reflectance")
        try:
            bid = self.core.add_bsdf(b.type, p)
        except (ValueError, TypeError) as e:
            src = b.source
            raise SceneError(f"bsdf '{b.type}': {e}", src.file if src else None,
                             src.line if src else None) from None
        self._bsdf[key] = bid
        return bid


def build_scene(desc: SceneDesc):
    """Create and commit the C++ scene for `desc`."""
    b = _Builder(desc)
    core = b.core
    for s in desc.shapes:
        src = s.source
        try:
            bid = b.bsdf(s.bsdf)
            if s.kind == "sphere":
                sid = core.add_sphere(np.asarray(s.center, dtype=np.float64).tolist(),
                                      float(s.radius), bid, bool(s.flip_normals))
            else:
                sid = core.add_mesh(
                    np.ascontiguousarray(s.positions, dtype=np.float32),
                    np.ascontiguousarray(s.indices, dtype=np.uint32),
                    None if s.normals is None else np.ascontiguousarray(s.normals, dtype=np.float32),
                    None if s.uvs is None else np.ascontiguousarray(s.uvs, dtype=np.float32),
                    bid,
                    bool(s.flip_normals),
                )
            if "caustic_receiver" in s.hints:
                core.set_caustic_receiver(sid)
            if s.emitter is not None:
                rad = np.asarray(s.emitter.params["radiance"], dtype=np.float64)
                core.add_area_emitter(sid, rad.tolist())
        except (ValueError, TypeError) as e:
            raise SceneError(f"shape '{s.id or s.kind}': {e}", src.file if src else None,
                             src.line if src else None) from None
    for e in desc.emitters:
        p = e.params
        src = e.source
        try:
            if e.type == "point":
                core.add_point_emitter(_v(p["intensity"]), _v(p["position"]))
            elif e.type == "spot":
                core.add_spot_emitter(_v(p["intensity"]), np.asarray(p["to_world"], dtype=np.float64),
                                      float(p.get("cutoff_angle", 20.0)),
                                      float(p.get("beam_width", 0.75 * p.get("cutoff_angle", 20.0))))
            elif e.type == "directional":
                core.add_directional_emitter(_v(p["irradiance"]), _v(p["direction"]))
            elif e.type == "constant":
                core.add_constant_emitter(_v(p["radiance"]))
            elif e.type == "envmap":
                core.add_envmap_emitter(np.ascontiguousarray(p["image"][:, :, :3], dtype=np.float32),
                                        float(p.get("scale", 1.0)),
                                        np.asarray(p.get("to_world", np.eye(4)), dtype=np.float64))
            else:
                raise SceneError(f"unsupported emitter type '{e.type}'",
                                 src.file if src else None, src.line if src else None)
        except (ValueError, TypeError) as ex:
            raise SceneError(f"emitter '{e.type}': {ex}", src.file if src else None,
                             src.line if src else None) from None
    c = desc.camera
    try:
        core.set_camera(
            np.asarray(c.to_world, dtype=np.float64), float(c.fov), c.fov_axis, float(c.near_clip),
            float(c.far_clip), int(c.width), int(c.height), [int(x) for x in c.crop],
            c.rfilter.type, float(c.rfilter.stddev), float(c.rfilter.radius),
        )
    except (ValueError, TypeError) as ex:
        src = c.source
        raise SceneError(f"sensor: {ex}", src.file if src else desc.filename,
                         src.line if src else None) from None
    try:
        core.commit()
    except RuntimeError as ex:
        raise SceneError(f"could not build the acceleration structure: {ex}", desc.filename) from None
    return core


def _v(x) -> list[float]:
    return np.broadcast_to(np.asarray(x, dtype=np.float64), (3,)).tolist()
