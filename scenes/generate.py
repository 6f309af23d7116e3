"""Deterministic generator of the textures (and, later, meshes) the scenes under
scenes/ use. Run `python scenes/generate.py`; it rewrites the files only when
their content would change. No randomness beyond a fixed-seed generator.
"""

from __future__ import annotations

import hashlib
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


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


OUTPUTS = {
    "textures/normalmap_bumps.exr": normalmap_bumps,
    "textures/sky.exr": sky,
}


def content_hash() -> str:
    """Hash of everything the generator produces (as arrays, independent of file encoding)."""
    h = hashlib.sha256()
    for name in sorted(OUTPUTS):
        h.update(name.encode())
        h.update(np.ascontiguousarray(OUTPUTS[name]()).tobytes())
    return h.hexdigest()


def main() -> int:
    for name, fn in OUTPUTS.items():
        path = os.path.join(HERE, name)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        changed = write_exr(path, fn())
        print(f"{'wrote' if changed else 'unchanged'} {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
