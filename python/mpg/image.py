"""Rendered images and their files: OpenEXR (linear float) and PNG (tone-mapped sRGB)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpg.errors import MPGError


@dataclass
class Image:
    """A rendered image.

    rgb:      float32 (H, W, 3), the per-pixel mean (linear radiance).
    variance: float32 (H, W, 3), the estimated variance of that mean (sample variance / spp).
    spp:      samples per pixel that went into it.
    stats:    the render statistics (see docs/design-notes.md).
    chain_rate_map: float32 (H, W), mpg's learned per-pixel chain rates, or None.
    delta_split_map: float32 (H, W), mpg's camera paths per sample for the light
              seen through delta scattering only (1: no split), or None.
    delta_branch_map: float32 (H, W), where those paths branch (1) or not (0),
              mpg's learned choice, or None (wherever the integrator branches).
    pixel_split_map: float32 (H, W), mpg's camera samples averaged per sample
              (1: no split), or None.
    """

    rgb: np.ndarray
    variance: np.ndarray
    spp: int
    stats: dict[str, Any] = field(default_factory=dict)
    chain_rate_map: np.ndarray | None = None
    delta_split_map: np.ndarray | None = None
    delta_branch_map: np.ndarray | None = None
    pixel_split_map: np.ndarray | None = None
    # render(record_classes=True): per pixel and class the sums of the samples'
    # parts and of their squares (mpg.render.CLASS_NAMES), else None
    class_sum: np.ndarray | None = None
    class_sum_sq: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.rgb.shape[0], self.rgb.shape[1]

    def write_exr(self, path: str, with_variance: bool = True) -> None:
        write_exr(path, self.rgb, self.variance if with_variance else None)

    def write_png(self, path: str, exposure: float = 0.0) -> None:
        write_png(path, self.rgb, exposure)


def _ensure_dir(path: str) -> None:
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)


def write_exr(path: str, rgb: np.ndarray, variance: np.ndarray | None = None) -> None:
    """Write linear RGB (and optionally a `variance` layer) as a float32 OpenEXR file."""
    import OpenEXR

    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise MPGError(f"write_exr: expected an (H, W, 3) image, got shape {rgb.shape}")
    channels: dict[str, np.ndarray] = {"RGB": rgb}
    if variance is not None:
        v = np.ascontiguousarray(variance, dtype=np.float32)
        for i, c in enumerate("RGB"):
            channels[f"variance.{c}"] = np.ascontiguousarray(v[:, :, i])
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    _ensure_dir(path)
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(path)
    except Exception as e:  # OpenEXR raises plain exceptions on I/O failures
        raise MPGError(f"{path}: could not write the EXR file: {e}") from None


def read_exr(path: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an RGB EXR (as written by write_exr or other tools): (rgb, variance or None)."""
    import OpenEXR

    try:
        with OpenEXR.File(path) as f:
            ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as e:
        raise MPGError(f"{path}: could not read the EXR file: {e}") from None
    if "RGB" in ch:
        rgb = ch["RGB"][:, :, :3]
    elif "RGBA" in ch:
        rgb = ch["RGBA"][:, :, :3]
    elif all(c in ch for c in "RGB"):
        rgb = np.stack([ch["R"], ch["G"], ch["B"]], axis=2)
    elif "Y" in ch:
        rgb = np.repeat(ch["Y"][:, :, None], 3, axis=2)
    else:
        raise MPGError(f"{path}: no RGB channels (found {sorted(ch)})")
    var = None
    if "variance" in ch and np.asarray(ch["variance"]).ndim == 3:
        var = np.asarray(ch["variance"])[:, :, :3].astype(np.float32)
    elif all(f"variance.{c}" in ch for c in "RGB"):
        var = np.stack([ch[f"variance.{c}"] for c in "RGB"], axis=2).astype(np.float32)
    return rgb.astype(np.float32), var


def to_srgb8(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB with an exposure in stops (clipped, no tone curve)."""
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.clip(x * (2.0 ** exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


def write_png(path: str, rgb: np.ndarray, exposure: float = 0.0) -> None:
    write_png8(path, to_srgb8(rgb, exposure))


def write_png8(path: str, rgb8: np.ndarray) -> None:
    """An 8-bit RGB array (H, W, 3) as it is, to a PNG file."""
    from PIL import Image as PILImage

    _ensure_dir(path)
    try:
        PILImage.fromarray(rgb8, mode="RGB").save(path)
    except OSError as e:
        raise MPGError(f"{path}: could not write the PNG file: {e}") from None
