"""Deterministic generator of the scene data under scenes/: the textures the
hand-written test scenes use (scenes/textures/) and the evaluation scenes of
the MPG paper's §6 (scenes/eval/: Mitsuba 3 XML, ASCII OBJ meshes, EXR textures
and one JSON sidecar per scene).

    python scenes/generate.py                  # (re)write; a file is rewritten only when it changes
    python scenes/generate.py --check          # exit 1 if a file on disk differs (or is missing / stale)
    python scenes/generate.py --contact-sheet  # render every eval scene at 96x96, 16 spp -> docs/images/eval_scenes.png

No randomness beyond numpy default_rng with fixed seeds. See docs/scenes.md.

The eval scenes mark casters / receivers / emitters with the SMS boolean flags
(caustic_caster_multi, caustic_receiver, caustic_emitter_multi); mpg keeps them
as hints. Mitsuba 3 (>= 3.6) rejects properties a plugin does not read, so load
these files in Mitsuba with `load_mitsuba()` below (unused properties ignored),
not with a bare `mi.load_file`.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
EVAL = "eval"


# --------------------------------------------------------------------------- textures (scenes/textures)

def normalmap_bumps(n: int = 128, bumps: int = 6) -> np.ndarray:
    """Tangent-space normal map of a smooth sinusoidal height field, encoded (n+1)/2."""
    y, x = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
    k = 2.0 * np.pi * bumps
    amp = 0.25 / k  # max slope 0.25
    # h = amp * sin(kx) * sin(ky): gradients analytically
    hx = amp * k * np.cos(k * x) * np.sin(k * y)
    hy = amp * k * np.sin(k * x) * np.cos(k * y)
    nrm = np.stack([-hx, -hy, np.ones_like(hx)], axis=2)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    return ((nrm + 1.0) * 0.5).astype(np.float32)


def sky(w: int = 128, h: int = 64) -> np.ndarray:
    """A latitude-longitude sky: blue gradient, dim ground, a warm sun blob."""
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    uu, vv = np.meshgrid(u, v)
    theta, phi = vv * np.pi, uu * 2 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], 2)
    up = np.clip(d[..., 1], 0, 1)[..., None]
    img = np.where(d[..., 1:2] > 0, (1 - up) * np.array([0.9, 0.95, 1.0]) + up * np.array([0.3, 0.5, 1.0]),
                   np.array([0.15, 0.12, 0.1]))
    sun = np.array([0.4, 0.75, 0.52])
    sun /= np.linalg.norm(sun)
    c = d @ sun
    img = img + np.exp((c[..., None] - 1.0) * 400.0) * np.array([60.0, 50.0, 40.0])
    return img.astype(np.float32)


# --------------------------------------------------------------------------- textures (scenes/eval/textures)

def normalmap_gaussian(n: int = 256, sigma_px: float = 6.0, max_slope_deg: float = 20.0,
                       seed: int = 7) -> np.ndarray:
    """Tileable tangent-space normal map of Gaussian-filtered white noise (the look of the
    paper's PLANE normal map), encoded (n+1)/2, steepest normal tilted max_slope_deg."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, n))
    f = np.fft.fftfreq(n)
    fy, fx = np.meshgrid(f, f, indexing="ij")
    kern = np.exp(-2.0 * (np.pi * sigma_px) ** 2 * (fx ** 2 + fy ** 2))
    spec = np.fft.fft2(noise) * kern
    # periodic derivatives in pixel units: d/dx <-> 2 pi i f
    hx = np.real(np.fft.ifft2(spec * 2j * np.pi * fx))
    hy = np.real(np.fft.ifft2(spec * 2j * np.pi * fy))
    scale = np.tan(np.radians(max_slope_deg)) / np.sqrt(hx ** 2 + hy ** 2).max()
    # image row 0 is sampled at v = 0 (top row); tangent y follows +v, i.e. down the rows
    nrm = np.stack([-hx * scale, -hy * scale, np.ones_like(hx)], axis=2)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    return ((nrm + 1.0) * 0.5).astype(np.float32)


def pool_tiles(n: int = 64, grout: int = 3) -> np.ndarray:
    """One square pool tile with grout on two edges (tiles when repeated), linear RGB."""
    img = np.empty((n, n, 3), np.float64)
    img[:] = (0.45, 0.68, 0.78)
    img[:grout, :] = (0.80, 0.82, 0.80)
    img[:, :grout] = (0.80, 0.82, 0.80)
    # slight darkening towards the tile centre, smooth
    y, x = np.meshgrid(np.arange(n) / n - 0.5, np.arange(n) / n - 0.5, indexing="ij")
    img[grout:, grout:] *= (1.0 - 0.12 * (x[grout:, grout:] ** 2 + y[grout:, grout:] ** 2))[..., None]
    return img.astype(np.float32)


# --------------------------------------------------------------------------- meshes

def _orient(faces: np.ndarray, P: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Flip triangles whose winding disagrees with their vertex normals (CCW seen from the normal side)."""
    a, b, c = P[faces[:, 0, 0]], P[faces[:, 1, 0]], P[faces[:, 2, 0]]
    g = np.cross(b - a, c - a)
    ns = N[faces[:, 0, 1]] + N[faces[:, 1, 1]] + N[faces[:, 2, 1]]
    bad = np.einsum("ij,ij->i", g, ns) < 0
    faces = faces.copy()
    faces[bad] = faces[bad][:, ::-1]
    return faces


def obj_text(P: np.ndarray, N: np.ndarray, faces: np.ndarray, comment: str) -> str:
    """ASCII OBJ: v, vn, f v//vn. faces: (m, 3, 2) 0-based (position, normal) indices."""
    N = N / np.linalg.norm(N, axis=1, keepdims=True)
    faces = _orient(faces, P, N)
    out = [f"# {comment}", "# generated by scenes/generate.py; do not edit"]
    out += ["v %.6f %.6f %.6f" % tuple(p) for p in P.tolist()]
    out += ["vn %.6f %.6f %.6f" % tuple(n) for n in N.tolist()]
    f1 = faces + 1
    out += ["f %d//%d %d//%d %d//%d" % tuple(f) for f in f1.reshape(-1, 6).tolist()]
    return "\n".join(out).replace("-0.000000", "0.000000") + "\n"


def _grid_faces(nx: int, nz: int, idx) -> list:
    tris = []
    for i in range(nx):
        for j in range(nz):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            tris += [(a, b, c), (a, c, d)]
    return tris


class Waves:
    """Height field h(x, z) = sum_i a_i cos(k_i . (x, z) + phi_i) with analytic gradient."""

    def __init__(self, seed: int, count: int, wl_min: float, wl_max: float, max_slope: float):
        rng = np.random.default_rng(seed)
        ang = rng.uniform(0.0, 2.0 * np.pi, count)
        wl = rng.uniform(wl_min, wl_max, count)
        k = 2.0 * np.pi / wl
        self.kx, self.kz = k * np.cos(ang), k * np.sin(ang)
        self.phi = rng.uniform(0.0, 2.0 * np.pi, count)
        amp = rng.uniform(0.5, 1.0, count) / k  # each wave's slope ~ the same order
        # bound of the slope: sum of a_i |k_i|
        self.amp = amp * max_slope / np.sum(amp * k)

    def h(self, x, z):
        arg = np.multiply.outer(x, self.kx) + np.multiply.outer(z, self.kz) + self.phi
        return np.cos(arg) @ self.amp

    def grad(self, x, z):
        arg = np.multiply.outer(x, self.kx) + np.multiply.outer(z, self.kz) + self.phi
        s = -np.sin(arg)
        return s @ (self.amp * self.kx), s @ (self.amp * self.kz)


def heightfield_surface(waves: Waves, half: float, n: int):
    """Open height-field surface over [-half, half]^2 at y = h, smooth analytic normals (up)."""
    t = np.linspace(-half, half, n + 1)
    X, Z = np.meshgrid(t, t, indexing="ij")
    H = waves.h(X, Z)
    hx, hz = waves.grad(X, Z)
    P = np.stack([X, H, Z], -1).reshape(-1, 3)
    N = np.stack([-hx, np.ones_like(hx), -hz], -1).reshape(-1, 3)
    idx = lambda i, j: i * (n + 1) + j  # noqa: E731
    tris = np.array(_grid_faces(n, n, idx))
    faces = np.stack([tris, tris], -1)
    return P, N, faces


def slab_mesh(waves: Waves, half: float, thickness: float, n: int):
    """Closed slab: bumpy height-field top at y = thickness + h (smooth normals), flat bottom at
    y = 0, four flat side walls. Boundary vertices are shared, so the mesh is watertight."""
    P, N, top = heightfield_surface(waves, half, n)
    P[:, 1] += thickness
    ntop = len(P)
    idx = lambda i, j: i * (n + 1) + j  # noqa: E731
    # boundary loop of the top, counter-clockwise around +y is irrelevant: _orient fixes windings
    loop = ([idx(i, 0) for i in range(n)] + [idx(n, j) for j in range(n)]
            + [idx(i, n) for i in range(n, 0, -1)] + [idx(0, j) for j in range(n, 0, -1)])
    m = len(loop)
    bottom = P[loop].copy()
    bottom[:, 1] = 0.0
    bidx = ntop + np.arange(m)
    centre = ntop + m
    P = np.concatenate([P, bottom, [[0.0, 0.0, 0.0]]])
    nb = len(N)
    N = np.concatenate([N, [[0, -1, 0], [0, 0, -1], [1, 0, 0], [0, 0, 1], [-1, 0, 0]]]).astype(float)
    faces = [f for f in top.tolist()]
    for k in range(m):
        k2 = (k + 1) % m
        faces.append([[centre, nb], [int(bidx[k2]), nb], [int(bidx[k]), nb]])
        side = k // n  # 0: z=-half, 1: x=+half, 2: z=+half, 3: x=-half
        wn = nb + 1 + side
        a, b = loop[k], loop[k2]
        faces.append([[a, wn], [b, wn], [int(bidx[k2]), wn]])
        faces.append([[a, wn], [int(bidx[k2]), wn], [int(bidx[k]), wn]])
    return P, N, np.array(faces)


def tube_mesh(radius: float, height: float, segments: int):
    """Open cylinder (no caps) around +y from y = 0 to height, smooth outward normals."""
    phi = 2.0 * np.pi * np.arange(segments) / segments
    c, s = np.cos(phi), np.sin(phi)
    ring = np.stack([radius * c, np.zeros_like(c), radius * s], -1)
    top = ring.copy()
    top[:, 1] = height
    P = np.concatenate([ring, top])
    N = np.stack([c, np.zeros_like(c), s], -1)
    faces = []
    for i in range(segments):
        j = (i + 1) % segments
        faces.append([[i, i], [j, j], [segments + j, j]])
        faces.append([[i, i], [segments + j, j], [segments + i, i]])
    return P, N, np.array(faces)


SLAB_HALF, SLAB_THICK, SLAB_N = 1.0, 0.12, 80
SLAB_WAVES = {"a": dict(seed=11, count=7, wl_min=0.3, wl_max=0.7, max_slope=0.4),
              "b": dict(seed=23, count=7, wl_min=0.3, wl_max=0.7, max_slope=0.4)}
POOL_HALF, POOL_DEPTH, WATER_LEVEL, POOL_N = 1.5, 1.5, -0.18, 110
POOL_WAVES = dict(seed=5, count=9, wl_min=0.3, wl_max=0.8, max_slope=0.5)
RING_RADIUS, RING_HEIGHT, RING_SEGMENTS = 1.0, 0.4, 256


def mesh_slab(variant: str) -> str:
    P, N, F = slab_mesh(Waves(**SLAB_WAVES[variant]), SLAB_HALF, SLAB_THICK, SLAB_N)
    return obj_text(P, N, F, f"glass slab '{variant}': {2 * SLAB_HALF} x {2 * SLAB_HALF}, bumpy top "
                             f"over y = {SLAB_THICK}, flat bottom at y = 0, closed")


def mesh_water() -> str:
    P, N, F = heightfield_surface(Waves(**POOL_WAVES), POOL_HALF, POOL_N)
    return obj_text(P, N, F, f"water surface: height field over [-{POOL_HALF}, {POOL_HALF}]^2 around y = 0, open")


def mesh_ring() -> str:
    P, N, F = tube_mesh(RING_RADIUS, RING_HEIGHT, RING_SEGMENTS)
    return obj_text(P, N, F, f"open cylinder r = {RING_RADIUS}, y in [0, {RING_HEIGHT}], smooth normals")


# --------------------------------------------------------------------------- XML helpers

def f(x) -> str:
    return f"{float(x):.6g}"


def vec(v) -> str:
    return ", ".join(f(x) for x in v)


def ind(text: str, n: int = 4) -> str:
    return "".join((" " * n + line if line.strip() else line) + "\n" for line in text.strip("\n").split("\n"))


HINT = '<boolean name="{}" value="true"/>'


def scene_xml(comment: str, max_depth: int, body: list) -> str:
    head = f"""<!-- {comment}
     Generated by scenes/generate.py; do not edit. The caustic_* booleans are SMS/MPG hints:
     load in Mitsuba 3 with scenes/generate.py load_mitsuba() (it ignores unused properties). -->
<scene version="3.0.0">
    <default name="res" value="256"/>
    <default name="spp" value="16"/>
    <default name="max_depth" value="{max_depth}"/>
    <integrator type="path">
        <integer name="max_depth" value="$max_depth"/>
    </integrator>
"""
    return head + "".join(ind(b) for b in body) + "</scene>\n"


def sensor(origin, target, fov, up=(0, 1, 0)) -> str:
    return f"""<sensor type="perspective">
    <float name="fov" value="{f(fov)}"/>
    <transform name="to_world">
        <lookat origin="{vec(origin)}" target="{vec(target)}" up="{vec(up)}"/>
    </transform>
    <sampler type="independent">
        <integer name="sample_count" value="$spp"/>
    </sampler>
    <film type="hdrfilm">
        <integer name="width" value="$res"/>
        <integer name="height" value="$res"/>
        <rfilter type="box"/>
    </film>
</sensor>"""


def diffuse(rgb=None, texture: str = "") -> str:
    if texture:
        return f'<bsdf type="diffuse">\n{ind(texture).rstrip()}\n</bsdf>'
    return f'<bsdf type="diffuse">\n    <rgb name="reflectance" value="{vec(rgb)}"/>\n</bsdf>'


def checker(name, c0, c1, scale) -> str:
    return f"""<texture name="{name}" type="checkerboard">
    <rgb name="color0" value="{vec(c0)}"/>
    <rgb name="color1" value="{vec(c1)}"/>
    <transform name="to_uv">
        <scale x="{f(scale[0])}" y="{f(scale[1])}"/>
    </transform>
</texture>"""


def bitmap(name, filename, scale) -> str:
    return f"""<texture name="{name}" type="bitmap">
    <string name="filename" value="{filename}"/>
    <transform name="to_uv">
        <scale x="{f(scale[0])}" y="{f(scale[1])}"/>
    </transform>
</texture>"""


def dielectric(ior) -> str:
    return f'<bsdf type="dielectric">\n    <float name="int_ior" value="{f(ior)}"/>\n</bsdf>'


def shape(kind: str, bsdf: str, transform: list = (), filename: str = "", hints=(), extra: str = "") -> str:
    lines = [f'<shape type="{kind}">']
    if filename:
        lines.append(f'    <string name="filename" value="{filename}"/>')
    lines += ["    " + HINT.format(h) for h in hints]
    if transform:
        lines.append('    <transform name="to_world">')
        lines += ["        " + t for t in transform]
        lines.append("    </transform>")
    lines.append(ind(bsdf).rstrip())
    if extra:
        lines.append(ind(extra).rstrip())
    lines.append("</shape>")
    return "\n".join(lines)


def floor(size: float, bsdf: str) -> str:
    return shape("rectangle", bsdf, [f'<scale value="{f(size)}"/>', '<rotate x="1" angle="-90"/>'],
                 hints=["caustic_receiver"])


def floor_checker(size=6.0, tiles=6.0) -> str:
    tex = checker("reflectance", (0.7, 0.7, 0.7), (0.45, 0.45, 0.48), (tiles, tiles))
    return floor(size, diffuse(texture=tex))


def disk_light(position, target, radius, radiance) -> str:
    d = np.subtract(target, position)
    up = (0, 0, 1) if abs(d[1]) > 0.9 * np.linalg.norm(d) else (0, 1, 0)
    emitter = f"""<emitter type="area">
    {HINT.format("caustic_emitter_multi")}
    <rgb name="radiance" value="{f(radiance)}"/>
</emitter>"""
    return shape("disk", diffuse((0, 0, 0)),
                 [f'<scale value="{f(radius)}"/>',
                  f'<lookat origin="{vec(position)}" target="{vec(target)}" up="{vec(up)}"/>'],
                 extra=emitter)


def point_light(position, intensity) -> str:
    return f"""<emitter type="point">
    {HINT.format("caustic_emitter_multi")}
    <point name="position" value="{vec(position)}"/>
    <rgb name="intensity" value="{f(intensity)}"/>
</emitter>"""


def slab(variant: str, y: float, x: float = 0.0, z: float = 0.0, rot: float = 0.0) -> str:
    tr = []
    if rot:
        tr.append(f'<rotate y="1" angle="{f(rot)}"/>')
    tr.append(f'<translate x="{f(x)}" y="{f(y)}" z="{f(z)}"/>')
    return shape("obj", dielectric(1.5), tr, filename=f"meshes/slab_{variant}.obj",
                 hints=["caustic_caster_multi"])


def cube(center, half, rgb, hints=()) -> str:
    return shape("cube", diffuse(rgb), [f'<scale x="{f(half[0])}" y="{f(half[1])}" z="{f(half[2])}"/>',
                                        f'<translate x="{f(center[0])}" y="{f(center[1])}" z="{f(center[2])}"/>'],
                 hints=hints)


# --------------------------------------------------------------------------- scenes

def light_dir(elev_deg: float, azim_deg: float) -> np.ndarray:
    """Unit vector towards the light: elevation above the floor, azimuth from +z towards +x."""
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    return np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])


# slab scenes share camera and light
SLAB_Y = 0.6                     # bottom of the (lowest) slab
SLAB_LIGHT_DIST = 4.5
SLAB_LIGHT_DIR = light_dir(55.0, 180.0)   # behind the slab: its caustic falls towards the camera
SLAB_LIGHT_R = 0.3
SLAB_LIGHT_L = 130.0
SLAB_CAM = dict(origin=(0.0, 4.6, 5.2), target=(0.0, 0.35, 0.3), fov=42.0)


def slab_light(radius=SLAB_LIGHT_R, radiance=SLAB_LIGHT_L, target=(0.0, SLAB_Y, 0.0)):
    pos = np.add(target, SLAB_LIGHT_DIST * SLAB_LIGHT_DIR)
    return disk_light(pos, target, radius, radiance)


def stacked_slabs(n: int, gap: float = 0.3, shift=(0.0, 0.0)) -> list:
    out = []
    for i in range(n):
        out.append(slab("ab"[i % 2], SLAB_Y + i * (SLAB_THICK + gap), x=shift[0] * i, z=shift[1] * i,
                        rot=90.0 * (i // 2)))
    return out


def slab_cam(n: int) -> dict:
    cam = dict(SLAB_CAM)
    if n > 2:  # frame the taller stacks: look higher, step back
        lift = 0.3 * (n - 2)
        cam.update(origin=(0.0, 4.6 + 2 * lift, 5.2 + 1.5 * lift), target=(0.0, 0.35 + lift, 0.3))
    return cam


def slab_scene(comment, n=1, max_depth=8, light=None, extra=(), shift=(0.0, 0.0)) -> str:
    body = [sensor(**slab_cam(n)), floor_checker(), *stacked_slabs(n, shift=shift),
            light or slab_light(), *extra]
    return scene_xml(comment, max_depth, body)


def pillars(count: int) -> list:
    """`count` square pillars standing on the floor under the slab, up to its bottom face."""
    if count == 0:
        return []
    if count <= 4:
        pos = [(-0.5, 0.0), (0.5, 0.0)] if count == 2 else [(-0.5, -0.45), (0.5, -0.45), (-0.5, 0.45),
                                                            (0.5, 0.45)]
    else:
        ang = 2 * np.pi * (np.arange(count) + 0.5) / count
        pos = list(zip(0.62 * np.cos(ang), 0.62 * np.sin(ang)))
    h = SLAB_Y / 2
    return [cube((x, h, z), (0.06, h, 0.06), (0.6, 0.6, 0.6)) for x, z in pos]


SPHERE_LIGHT_POS = (np.array([0.0, 1.0, 0.0]) + 6.0 * light_dir(40.0, -90.0))
SPHERE_LIGHT_R, SPHERE_LIGHT_L = 0.3, 300.0
SPHERE_CAM = dict(origin=(0.0, 4.2, 6.0), target=(0.6, 0.5, 0.0), fov=40.0)


def sphere_scene(point: bool) -> str:
    glass = shape("sphere", dielectric(1.5), ['<scale value="1"/>', '<translate y="1"/>'],
                  hints=["caustic_caster_multi"])
    if point:
        light = point_light(SPHERE_LIGHT_POS, SPHERE_LIGHT_L * np.pi * SPHERE_LIGHT_R ** 2)
        what = "a point light"
    else:
        light = disk_light(SPHERE_LIGHT_POS, (0, 1, 0), SPHERE_LIGHT_R, SPHERE_LIGHT_L)
        what = f"a small disk light (r = {SPHERE_LIGHT_R})"
    return scene_xml(f"SPHERE: glass sphere (IOR 1.5, r = 1) on a diffuse floor, {what} at 40 deg elevation.",
                     8, [sensor(**SPHERE_CAM), floor_checker(), glass, light])


RING_LIGHT_POS = 6.0 * light_dir(35.0, -125.0)
RING_LIGHT_R, RING_LIGHT_L = 0.25, 1200.0
RING_CAM = dict(origin=(0.0, 3.4, 2.6), target=(0.0, 0.0, 0.1), fov=44.0)


def ring_scene() -> str:
    gold = '<bsdf type="twosided">\n    <bsdf type="conductor">\n        <string name="material" value="Au"/>\n    </bsdf>\n</bsdf>'
    ring = shape("obj", gold, filename="meshes/ring.obj", hints=["caustic_caster_multi"])
    fl = floor(6.0, diffuse((0.12, 0.12, 0.15)))
    return scene_xml("RING: a gold ring (open cylinder, twosided conductor) on a diffuse floor, small disk light "
                     "low on one side: cardioid caustic inside (R chains).", 8,
                     [sensor(**RING_CAM), fl, ring, disk_light(RING_LIGHT_POS, (0, 0.2, 0), RING_LIGHT_R, RING_LIGHT_L)])


SUN_DIST, SUN_ANGLE_DEG, SUN_RADIANCE = 40.0, 4.0, 135.0
POOL_CAM = dict(origin=(0.6, 4.2, 3.3), target=(0.0, -0.8, 0.0), fov=42.0)


def pool_scene() -> str:
    W, D, L = POOL_HALF, POOL_DEPTH, 4.0
    tiles = 4.0  # tiles per unit
    tex = lambda sx, sy: diffuse(texture=bitmap("reflectance", "textures/pool_tiles.exr", (sx, sy)))  # noqa: E731
    body = [sensor(**POOL_CAM)]
    body.append(shape("rectangle", tex(2 * W * tiles, 2 * W * tiles),
                      [f'<scale value="{f(W)}"/>', '<rotate x="1" angle="-90"/>', f'<translate y="{f(-D)}"/>'],
                      hints=["caustic_receiver"]))
    for ang, (tx, tz) in ((90, (-W, 0)), (-90, (W, 0)), (0, (0, -W)), (180, (0, W))):
        body.append(shape("rectangle", tex(2 * W * tiles, D * tiles),
                          [f'<scale x="{f(W)}" y="{f(D / 2)}"/>', f'<rotate y="1" angle="{ang}"/>',
                           f'<translate x="{f(tx)}" y="{f(-D / 2)}" z="{f(tz)}"/>'],
                          hints=["caustic_receiver"]))
    deck = diffuse((0.5, 0.46, 0.4))
    # deck around the pool at y = 0: [-L, L]^2 minus [-W, W]^2, four strips
    for cx, cz, hx, hz in ((0, (L + W) / 2, L, (L - W) / 2), (0, -(L + W) / 2, L, (L - W) / 2),
                           ((L + W) / 2, 0, (L - W) / 2, W), (-(L + W) / 2, 0, (L - W) / 2, W)):
        body.append(shape("rectangle", deck, [f'<scale x="{f(hx)}" y="{f(hz)}"/>', '<rotate x="1" angle="-90"/>',
                                              f'<translate x="{f(cx)}" z="{f(cz)}"/>']))
    body.append(shape("obj", dielectric(1.33), [f'<translate y="{f(WATER_LEVEL)}"/>'],
                      filename="meshes/water.obj", hints=["caustic_caster_multi"]))
    sun = SUN_DIST * light_dir(60.0, 150.0)
    body.append(disk_light(sun, (0, 0, 0), SUN_DIST * np.tan(np.radians(SUN_ANGLE_DEG)), SUN_RADIANCE))
    return scene_xml(f"POOL: water surface height field (IOR 1.33) over a tiled pool, small distant disk light "
                     f"({SUN_ANGLE_DEG} deg angular radius, 60 deg elevation) as the sun (T chains).", 8, body)


PLANE_LIGHT = (0.0, 3.3, 4.0)
PLANE_PANEL = dict(half=(1.2, 0.9), y=1.3, z=-0.6)
PLANE_CAM = dict(origin=(0.0, 1.6, 6.0), target=(0.0, 0.6, 0.0), fov=45.0)


def plane_scene() -> str:
    nm = """<bsdf type="normalmap">
    <texture name="normalmap" type="bitmap">
        <string name="filename" value="textures/normalmap_gaussian.exr"/>
        <boolean name="raw" value="true"/>
    </texture>
    <bsdf type="roughconductor">
        <string name="material" value="Cu"/>
        <string name="distribution" value="ggx"/>
        <float name="alpha" value="0.002"/>
    </bsdf>
</bsdf>"""
    hx, hy = PLANE_PANEL["half"]
    panel = shape("rectangle", nm, [f'<scale x="{f(hx)}" y="{f(hy)}"/>',
                                    f'<translate y="{f(PLANE_PANEL["y"])}" z="{f(PLANE_PANEL["z"])}"/>'],
                  hints=["caustic_caster_multi"])
    glossy = f"""<bsdf type="roughconductor">
    <string name="distribution" value="beckmann"/>
    <float name="alpha" value="0.05"/>
{ind(checker("specular_reflectance", (0.75, 0.75, 0.75), (0.45, 0.45, 0.5), (16, 16)), 4).rstrip()}
</bsdf>"""
    fl = floor(8.0, glossy)
    light = disk_light(PLANE_LIGHT, (0, 1.3, -0.6), 0.2, 300.0)
    env = '<emitter type="constant">\n    <rgb name="radiance" value="0.25"/>\n</emitter>'
    return scene_xml("PLANE: a normal-mapped copper panel (roughconductor GGX alpha 0.002) over a glossy floor "
                     "(roughconductor Beckmann alpha 0.05), small disk light, dim constant environment.", 8,
                     [sensor(**PLANE_CAM), fl, panel, light, env])


def room_scene() -> str:
    white, red, green = (0.7, 0.7, 0.7), (0.65, 0.12, 0.1), (0.15, 0.5, 0.15)
    rect = lambda rgb, tr: shape("rectangle", diffuse(rgb), tr)  # noqa: E731
    body = [sensor((0.0, 1.0, 3.6), (0.0, 1.0, 0.0), 39.0),
            rect(white, ['<rotate x="1" angle="-90"/>']),
            rect(white, ['<rotate x="1" angle="90"/>', '<translate y="2"/>']),
            rect(white, ['<translate y="1" z="-1"/>']),
            rect(red, ['<rotate y="1" angle="90"/>', '<translate x="-1" y="1"/>']),
            rect(green, ['<rotate y="1" angle="-90"/>', '<translate x="1" y="1"/>']),
            shape("cube", diffuse(white), ['<scale x="0.3" y="0.6" z="0.3"/>', '<rotate y="1" angle="20"/>',
                                           '<translate x="-0.35" y="0.6" z="-0.35"/>']),
            shape("cube", diffuse(white), ['<scale value="0.28"/>', '<rotate y="1" angle="-18"/>',
                                           '<translate x="0.38" y="0.28" z="0.3"/>']),
            shape("rectangle", diffuse((0, 0, 0)), ['<scale x="0.25" y="0.2"/>', '<rotate x="1" angle="90"/>',
                                                    '<translate y="1.995"/>'],
                  extra='<emitter type="area">\n    <rgb name="radiance" value="17"/>\n</emitter>')]
    return scene_xml("DIFFUSE ROOM: a closed-on-five-sides diffuse box room, two boxes, ceiling area light; "
                     "no specular object (MPG must cost nothing here).", 8, body)


# --------------------------------------------------------------------------- caustic boxes

def project(cam: dict, pts, res: int = 256) -> np.ndarray:
    """World points -> normalised image coordinates (x right, y down) of a square perspective camera
    with fov along x (Mitsuba's convention: camera +x is image left)."""
    o, t = np.array(cam["origin"], float), np.array(cam["target"], float)
    fw = (t - o) / np.linalg.norm(t - o)
    left = np.cross((0.0, 1.0, 0.0), fw)
    left /= np.linalg.norm(left)
    up = np.cross(fw, left)
    d = np.asarray(pts, float) - o
    z = d @ fw
    tn = np.tan(np.radians(cam["fov"]) / 2)
    return np.stack([0.5 - 0.5 * (d @ left) / (z * tn), 0.5 - 0.5 * (d @ up) / (z * tn)], -1)


def to_floor(light, pts, y: float = 0.0) -> np.ndarray:
    """Central projection of points from a point light onto the plane at height y."""
    light = np.asarray(light, float)
    p = np.asarray(pts, float)
    s = (light[1] - y) / (light[1] - p[:, 1])
    return light + (p - light) * s[:, None]


def box_of(cam, pts, margin: float = 0.02) -> list:
    uv = project(cam, pts)
    lo, hi = np.clip(uv.min(0) - margin, 0, 1), np.clip(uv.max(0) + margin, 0, 1)
    return [round(float(v), 3) for v in (lo[0], lo[1], hi[0], hi[1])]


def slab_box(cam, n, shift=(0.0, 0.0), light_pos=None) -> list:
    """The floor region lit through the slabs (their shadow from the light's centre), in the image."""
    light_pos = np.add((0.0, SLAB_Y, 0.0), SLAB_LIGHT_DIST * SLAB_LIGHT_DIR) if light_pos is None else light_pos
    pts = []
    for i in range(n):
        y0 = SLAB_Y + i * (SLAB_THICK + 0.3)
        for x in (-SLAB_HALF, SLAB_HALF):
            for z in (-SLAB_HALF, SLAB_HALF):
                for y in (y0, y0 + SLAB_THICK):
                    pts.append((x + shift[0] * i, y, z + shift[1] * i))
    return box_of(cam, to_floor(light_pos, pts))


def sphere_box() -> list:
    u = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    v = np.linspace(0.05, np.pi - 0.05, 32)
    U, V = np.meshgrid(u, v)
    pts = np.stack([np.sin(V) * np.cos(U), 1 + np.cos(V), np.sin(V) * np.sin(U)], -1).reshape(-1, 3)
    pts = pts[pts[:, 1] < SPHERE_LIGHT_POS[1] - 0.05]
    return box_of(SPHERE_CAM, to_floor(SPHERE_LIGHT_POS, pts))


def ring_box() -> list:
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    return box_of(RING_CAM, np.stack([RING_RADIUS * np.cos(a), 0 * a, RING_RADIUS * np.sin(a)], -1))


def pool_box() -> list:
    W = POOL_HALF
    pts = [(x, y, z) for x in (-W, W) for z in (-W, W) for y in (-POOL_DEPTH, WATER_LEVEL)]
    return box_of(POOL_CAM, pts, margin=0.0)


def plane_box() -> list:
    """The glossy floor shows the caustic where it mirrors the panel: the panel's mirror image."""
    hx, hy = PLANE_PANEL["half"]
    pts = [(x, -(PLANE_PANEL["y"] + y), PLANE_PANEL["z"]) for x in (-hx, hx) for y in (-hy, hy)]
    return box_of(PLANE_CAM, pts, margin=0.0)


EMITTER_SIZES = (0.01, 0.03, 0.1, 0.3, 1.0)
VISIBILITY = (0, 2, 4, 8)
CHAIN_LENGTHS = (1, 2, 3, 4)


def scenes() -> dict:
    """name -> dict(xml, sidecar fields except name)."""
    S = {}

    def add(name, xml, description, chains, reference, series=None, box=None, fill=None):
        S[name] = dict(xml=xml, description=description, chains=chains, series=series,
                       caustic_box=None if box is None else [float(b) for b in box], reference=reference,
                       fill=fill)

    ref_area = ("mitsuba ptracer+path: small area light, the caustic on the directly seen floor converges "
                "fastest with ptracer; path for the pixels seen through glass, which ptracer cannot reach")
    add("sphere", sphere_scene(False), "Glass sphere (IOR 1.5) on a checkered diffuse floor, small disk light.",
        ["TT"], ref_area, box=sphere_box())
    add("sphere_point", sphere_scene(True), "As sphere, lit by a point light of the same power toward the sphere.",
        ["TT"], "mitsuba ptracer: a point light seen through glass is unreachable for path tracing; the floor "
        "seen through the sphere (L-TT-D-TT-E) is unreachable for both of Mitsuba's renderers, so the pixels "
        "the light tracer cannot see are rendered by reference_fill",
        box=sphere_box(), fill="sms_star")
    add("slab", slab_scene("SLAB: a glass slab with a bumpy top (IOR 1.5) over a diffuse floor, small disk light."),
        "Glass slab (IOR 1.5), bumpy height-field top, flat bottom, over a checkered floor, small disk light.",
        ["TT"], ref_area, box=slab_box(SLAB_CAM, 1))
    add("double_slabs", slab_scene("DOUBLE SLABS: two bumpy glass slabs stacked with a gap, offset sideways.", n=2,
                                   max_depth=10, shift=(0.7, 0.0)),
        "Two bumpy glass slabs stacked with a 0.35 gap, offset sideways: TT where light crosses one slab, "
        "TTTT where it crosses both.", ["TT", "TTTT"], ref_area, box=slab_box(SLAB_CAM, 2, (0.7, 0.0)))
    add("ring", ring_scene(), "Gold ring (open cylinder, both sides reflective) on a diffuse floor, small light "
        "low on one side: cardioid caustic inside the ring.", ["R", "RR"],
        "mitsuba ptracer+path: ptracer for the floor (seen directly), path for the reflections in the ring",
        box=ring_box())
    add("pool", pool_scene(), "Water surface height field (IOR 1.33) over a tiled pool with walls and a deck; "
        "small distant disk light as the sun.", ["T"],
        "mitsuba path: the pool floor is seen through the water (L-T-D-T-E), which ptracer cannot connect; "
        "the sun is an area light, so path tracing converges (slowly)", box=pool_box())
    add("plane", plane_scene(), "Normal-mapped copper panel (GGX alpha 0.002) above a glossy checkered floor "
        "(roughconductor alpha 0.05), small disk light, dim constant environment.", ["R"],
        "mitsuba path: glossy receiver (alpha 0.05) seen directly, small area light; ptracer would also work, "
        "path is simpler", box=plane_box())
    add("diffuse_room", room_scene(), "Diffuse box room with two boxes and a ceiling area light; no specular "
        "object at all.", [], "mitsuba path: purely diffuse", box=None)
    for n in CHAIN_LENGTHS:
        md = max(8, 4 * n + 2)
        add(f"chain_length_{n}", slab_scene(f"CHAIN LENGTH {n}: {n} bumpy glass slab(s) stacked with gaps "
                                            f"(Fig. 16, top row).", n=n, max_depth=md),
            f"{n} bumpy glass slab(s) stacked with 0.35 gaps over a diffuse floor, small disk light "
            f"(caustic chain of {2 * n} refractions).", ["T" * (2 * n)], ref_area,
            series={"name": "chain_length", "value": n}, box=slab_box(slab_cam(n), n))
    for k in VISIBILITY:
        add(f"visibility_{k}", slab_scene(f"VISIBILITY {k}: bumpy glass slab with {k} pillars below casting "
                                          f"shadows into its caustic (Fig. 16, middle row).", extra=pillars(k)),
            f"The slab scene with {k} square diffuse pillars between slab and floor.", ["TT"], ref_area,
            series={"name": "visibility", "value": k}, box=slab_box(SLAB_CAM, 1))
    for r in EMITTER_SIZES:
        radius = r  # scene units (the slab is 2 x 2, the light 5.5 away)
        rad = SLAB_LIGHT_L * (SLAB_LIGHT_R / radius) ** 2
        name = f"emitter_size_{int(round(r * 100)):03d}"
        add(name, slab_scene(f"EMITTER SIZE {r}: the slab scene, disk light radius {f(radius)} (power constant "
                             f"across the series; Fig. 16, bottom row).", light=slab_light(radius, rad)),
            f"The slab scene with a disk light of radius {f(radius)} (relative size {r}); radiance scaled "
            f"as 1/r^2 to keep the power constant.", ["TT"],
            ref_area if r >= 0.1 else "mitsuba ptracer+path: tiny light, ptracer for the directly seen floor "
            "(path tracing hardly hits it); path for the pixels seen through glass",
            series={"name": "emitter_size", "value": r}, box=slab_box(SLAB_CAM, 1))
    return S


# --------------------------------------------------------------------------- outputs

def outputs() -> dict:
    """Every generated file, relative to scenes/: name -> ('exr', fn -> array) or ('text', fn -> str)."""
    out = {
        "textures/normalmap_bumps.exr": ("exr", normalmap_bumps),
        "textures/sky.exr": ("exr", sky),
        f"{EVAL}/textures/normalmap_gaussian.exr": ("exr", normalmap_gaussian),
        f"{EVAL}/textures/pool_tiles.exr": ("exr", pool_tiles),
        f"{EVAL}/meshes/slab_a.obj": ("text", lambda: mesh_slab("a")),
        f"{EVAL}/meshes/slab_b.obj": ("text", lambda: mesh_slab("b")),
        f"{EVAL}/meshes/water.obj": ("text", mesh_water),
        f"{EVAL}/meshes/ring.obj": ("text", mesh_ring),
    }
    for name, s in scenes().items():
        side = {"name": name, "description": s["description"], "chains": s["chains"], "series": s["series"],
                "caustic_box": s["caustic_box"], "reference": s["reference"]}
        if s["fill"]:
            side["reference_fill"] = s["fill"]    # mpg-bench reference --fill
        out[f"{EVAL}/{name}.xml"] = ("text", (lambda x: lambda: x)(s["xml"]))
        out[f"{EVAL}/{name}.json"] = ("text", (lambda x: lambda: json.dumps(x, indent=2) + "\n")(side))
    return out


def _produce(kind, fn):
    v = fn()
    return np.ascontiguousarray(v) if kind == "exr" else v.encode()


def content_hash() -> str:
    """SHA-256 over every generated file's name and content (EXR: its float array, shape and dtype;
    text files: their bytes), in sorted name order. Independent of the EXR encoder."""
    h = hashlib.sha256()
    outs = outputs()
    for name in sorted(outs):
        kind, fn = outs[name]
        v = _produce(kind, fn)
        h.update(name.encode() + b"\0")
        if kind == "exr":
            h.update(f"{v.shape}{v.dtype}".encode())
            h.update(v.tobytes())
        else:
            h.update(v)
    return h.hexdigest()


def write_exr(path: str, rgb: np.ndarray) -> bool:
    import OpenEXR

    tmp = path + ".tmp.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": np.ascontiguousarray(rgb)}) as f:
        f.write(tmp)
    old = open(path, "rb").read() if os.path.exists(path) else None
    new = open(tmp, "rb").read()
    if old == new:
        os.remove(tmp)
        return False
    os.replace(tmp, path)
    return True


def read_exr_rgb(path: str) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(path) as fh:
        ch = fh.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels)
        return np.stack([np.asarray(ch[c].pixels) for c in "RGB"], -1)


def write_text(path: str, data: bytes) -> bool:
    if os.path.exists(path) and open(path, "rb").read() == data:
        return False
    tmp = path + ".tmp"
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)
    return True


def _differs(path: str, kind: str, v) -> str:
    if not os.path.exists(path):
        return "missing"
    if kind == "exr":
        try:
            old = read_exr_rgb(path)
        except Exception as e:  # noqa: BLE001
            return f"unreadable ({e})"
        return "" if (old.shape == v.shape and old.dtype == v.dtype and np.array_equal(old, v)) else "differs"
    return "" if open(path, "rb").read() == v else "differs"


def stale_files(outs: dict) -> list:
    """Files under scenes/eval/ the generator does not produce."""
    known = {os.path.normpath(n) for n in outs}
    stale = []
    for d, _, files in os.walk(os.path.join(HERE, EVAL)):
        for fn in files:
            rel = os.path.normpath(os.path.relpath(os.path.join(d, fn), HERE))
            if rel not in known:
                stale.append(rel)
    return sorted(stale)


def generate(check: bool = False) -> int:
    outs = outputs()
    bad = 0
    for name in sorted(outs):
        kind, fn = outs[name]
        v = _produce(kind, fn)
        path = os.path.join(HERE, name)
        if check:
            why = _differs(path, kind, v)
            if why:
                print(f"{why}: scenes/{name}")
                bad += 1
            continue
        os.makedirs(os.path.dirname(path), exist_ok=True)
        changed = write_exr(path, v) if kind == "exr" else write_text(path, v)
        print(f"{'wrote' if changed else 'unchanged'} {name}")
    for name in stale_files(outs):
        print(f"stale (not generated): scenes/{name}")
        bad += check
    if check:
        print("scenes are up to date" if not bad else f"{bad} file(s) out of date: run python scenes/generate.py")
    return 1 if bad else 0


# --------------------------------------------------------------------------- Mitsuba 3 and previews

def load_mitsuba(path: str, variant: str = "scalar_rgb", **params):
    """Load an eval scene in Mitsuba 3 (>= 3.6), ignoring the SMS/MPG hint booleans that
    Mitsuba's plugins do not read. params: <default> overrides as strings (res="64")."""
    import mitsuba as mi

    mi.set_variant(variant)
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    folder = os.path.dirname(os.path.abspath(str(path)))
    if folder not in [str(p) for p in fr]:
        fr.prepend(folder)  # what mi.load_file does: meshes and textures relative to the scene
    cfg = mi.parser.ParserConfig(variant)
    cfg.unused_properties = mi.LogLevel.Debug
    state = mi.parser.parse_file(cfg, str(path), **{k: str(v) for k, v in params.items()})
    mi.parser.transform_upgrade(cfg, state)
    mi.parser.transform_resolve(cfg, state)
    return mi.parser.instantiate(cfg, state)


def eval_scene_paths() -> list:
    return [os.path.join(HERE, EVAL, f"{n}.xml") for n in scenes()]


def contact_sheet(path: str = os.path.join(ROOT, "docs", "images", "eval_scenes.png"), res: int = 96,
                  spp: int = 16, cols: int = 6) -> str:
    """Render every eval scene with mpg's path tracer at res x res, spp and tile them with labels."""
    from PIL import Image, ImageDraw

    import mpg
    from mpg.image import to_srgb8

    names = list(scenes())
    label_h = 12
    rows = (len(names) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * res, rows * (res + label_h)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, name in enumerate(names):
        img = mpg.render(mpg.load_file(os.path.join(HERE, EVAL, f"{name}.xml"), res=str(res)), spp=spp,
                         seed=0, progress=False)
        x, y = (i % cols) * res, (i // cols) * (res + label_h)
        sheet.paste(Image.fromarray(to_srgb8(img.rgb)), (x, y))
        draw.text((x + 2, y + res), name, fill=(0, 0, 0))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    sheet.save(path, optimize=True)
    return path


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--contact-sheet" in argv:
        print("wrote", contact_sheet())
        return 0
    return generate(check="--check" in argv)


if __name__ == "__main__":
    sys.exit(main())
