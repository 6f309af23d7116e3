"""The scene description: what the XML loader produces and the C++ builder consumes.

Everything here is plain data in *world space*: transforms are already applied,
meshes are numpy arrays, textures are decoded float32 images in linear RGB.
The loader (``mpg.scene.loader``) validates; ``mpg.scene.build`` hands this to
the C++ core without further checks beyond array shapes.

Conventions (Mitsuba 3's, so the same file gives the same image in both):
- Spectra are linear RGB triples (numpy float64, shape (3,)).
- Camera local frame: +z forward, +y up, +x *left* (Mitsuba's ``lookat``).
- UVs: as Mitsuba 3 produces them for each shape; bitmap row 0 is v = 0 after
  Mitsuba's convention (the loader flips images so that ``image[0]`` is the
  row sampled at v = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class SourcePos:
    """Where an element came from, for error messages."""

    file: str
    line: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


@dataclass
class TextureDesc:
    """A spectrum- or float-valued texture.

    kind: 'constant'     -> value (3,)
          'bitmap'       -> image float32 (H, W, 3) linear; filter 'bilinear'|'nearest';
                            wrap 'repeat'|'mirror'|'clamp'
          'checkerboard' -> color0 (3,), color1 (3,)
    to_uv: 3x3 affine matrix applied to (u, v, 1) before lookup.
    """

    kind: str
    value: np.ndarray | None = None
    image: np.ndarray | None = None
    color0: np.ndarray | None = None
    color1: np.ndarray | None = None
    to_uv: np.ndarray = field(default_factory=lambda: np.eye(3))
    filter: str = "bilinear"
    wrap: str = "repeat"
    source: SourcePos | None = None

    @staticmethod
    def constant(v: Any) -> TextureDesc:
        a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,)).copy()
        return TextureDesc(kind="constant", value=a)


@dataclass
class BSDFDesc:
    """A BSDF with its parameters resolved to final values.

    type and params (all present, defaults filled by the loader):
      diffuse:        reflectance: TextureDesc
      conductor:      eta (3,), k (3,), specular_reflectance: TextureDesc
      roughconductor: eta, k, specular_reflectance, alpha_u: float, alpha_v: float,
                      distribution: 'ggx'|'beckmann', sample_visible: bool
      dielectric:     int_ior: float, ext_ior: float, specular_reflectance, specular_transmittance
      roughdielectric: dielectric's + alpha: float, distribution, sample_visible
      thindielectric: int_ior, ext_ior, specular_reflectance, specular_transmittance
      plastic:        diffuse_reflectance: TextureDesc, specular_reflectance: TextureDesc,
                      int_ior, ext_ior, nonlinear: bool
      twosided:       front: BSDFDesc, back: BSDFDesc (the same object when one child is given)
      normalmap:      nested: BSDFDesc, normalmap: TextureDesc (bitmap, raw values in [0,1],
                      NOT gamma-decoded; tangent-space normal = 2*value - 1)
      null:           (nothing)
    """

    type: str
    params: dict[str, Any] = field(default_factory=dict)
    id: str | None = None
    source: SourcePos | None = None


@dataclass
class EmitterDesc:
    """An emitter.

    type and params:
      area:        radiance: (3,)              (attached to a ShapeDesc)
      point:       intensity (3,), position (3,)
      spot:        intensity (3,), to_world 4x4 (local +z is the spot axis, origin the position),
                   cutoff_angle (deg), beam_width (deg)
      directional: irradiance (3,), direction (3,) (normalised, direction light travels)
      constant:    radiance (3,)
      envmap:      image float32 (H, W, 3) linear latitude-longitude, scale: float,
                   to_world 4x4 (Mitsuba convention: local +y up, u along phi)
    hints: the SMS/MPG flags found on the element (e.g. 'caustic_emitter_single').
    """

    type: str
    params: dict[str, Any] = field(default_factory=dict)
    hints: set[str] = field(default_factory=set)
    source: SourcePos | None = None


@dataclass
class ShapeDesc:
    """A shape in world space.

    kind 'mesh':   positions float32 (N,3), indices uint32 (M,3), normals float32 (N,3) or
                   None (face normals), uvs float32 (N,2) or None.
    kind 'sphere': center (3,), radius float (an exact sphere).
    flip_normals:  applied already to mesh normals/winding? No: kept as a flag; the core
                   flips the geometric and shading normal.
    hints:         SMS/MPG shape flags ('caustic_caster_single', 'caustic_receiver', ...).
    """

    kind: str
    bsdf: BSDFDesc
    positions: np.ndarray | None = None
    indices: np.ndarray | None = None
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    center: np.ndarray | None = None
    radius: float = 0.0
    flip_normals: bool = False
    emitter: EmitterDesc | None = None
    hints: set[str] = field(default_factory=set)
    id: str | None = None
    source: SourcePos | None = None


@dataclass
class FilterDesc:
    type: str = "box"          # 'box' | 'gaussian' | 'tent'
    stddev: float = 0.5        # gaussian
    radius: float = 1.0        # tent (gaussian radius is 4*stddev as in Mitsuba 3)


@dataclass
class CameraDesc:
    fov: float = 45.0                 # degrees, along fov_axis
    fov_axis: str = "x"               # 'x'|'y'|'diagonal'|'smaller'|'larger'
    to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    near_clip: float = 1e-2
    far_clip: float = 1e4
    width: int = 768
    height: int = 576
    crop: tuple[int, int, int, int] = (0, 0, 768, 576)   # offset_x, offset_y, width, height
    rfilter: FilterDesc = field(default_factory=FilterDesc)
    spp: int = 4                      # the sampler's sample_count
    sampler: str = "independent"      # 'independent' | 'stratified' (pixel positions, render.py)
    source: SourcePos | None = None


@dataclass
class IntegratorDesc:
    type: str = "path"
    params: dict[str, Any] = field(default_factory=dict)   # max_depth, rr_depth, hide_emitters...
    source: SourcePos | None = None


@dataclass
class SceneDesc:
    shapes: list[ShapeDesc] = field(default_factory=list)
    emitters: list[EmitterDesc] = field(default_factory=list)   # non-area emitters
    camera: CameraDesc = field(default_factory=CameraDesc)
    integrator: IntegratorDesc = field(default_factory=IntegratorDesc)
    filename: str | None = None
    warnings: list[str] = field(default_factory=list)
