"""Image reading for textures and environment maps.

Returns float32 (H, W, 3) arrays, row 0 = the first (top) row of the file.
Mitsuba 3 samples the top row of a bitmap at v = 0 (and its OBJ reader flips
the files' v), so keeping the file's row order is what makes `image[0]` the
row sampled at v = 0. 8- and 16-bit images (PNG, JPEG, ...) are decoded from
sRGB to linear unless `raw`; EXR is linear already. Greyscale becomes three
equal channels; alpha is dropped.
"""

from __future__ import annotations

import os

import numpy as np

from mpg.errors import SceneError

_cache: dict[tuple[str, float, bool], np.ndarray] = {}

_SRGB_LUT8 = None


def _srgb_lut8() -> np.ndarray:
    global _SRGB_LUT8
    if _SRGB_LUT8 is None:
        c = np.arange(256, dtype=np.float64) / 255.0
        _SRGB_LUT8 = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)
    return _SRGB_LUT8


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _to_rgb(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        a = a[:, :, None]
    c = a.shape[2]
    if c == 1:
        return np.repeat(a, 3, axis=2)
    if c == 2:      # grey + alpha
        return np.repeat(a[:, :, :1], 3, axis=2)
    return a[:, :, :3]


def _read_exr(path: str) -> np.ndarray:
    try:
        import OpenEXR
    except ImportError:
        raise SceneError("reading EXR images needs the 'OpenEXR' Python package", path) from None
    try:
        with OpenEXR.File(path) as f:
            ch = f.parts[0].channels
            names = list(ch.keys())
            if "RGB" in ch:
                img = ch["RGB"].pixels
            elif "RGBA" in ch:
                img = ch["RGBA"].pixels[:, :, :3]
            elif all(k in ch for k in "RGB"):
                img = np.stack([ch[k].pixels for k in "RGB"], axis=2)
            elif "Y" in ch:
                img = ch["Y"].pixels
            elif len(names) == 1:
                img = ch[names[0]].pixels
            else:
                raise SceneError(f"EXR has no RGB or Y channels (channels: {', '.join(names)})", path)
            img = np.array(img, dtype=np.float32)
    except SceneError:
        raise
    except Exception as e:  # noqa: BLE001 - the OpenEXR binding raises plain exceptions
        raise SceneError(f"could not read EXR image: {e}", path) from None
    return _to_rgb(img)


def _read_ldr(path: str, raw: bool) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
                mode = im.mode
            if mode in ("1", "CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
                mode = "RGB"
            a = np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise SceneError(f"could not read image: {e}", path) from None
    if a.dtype == np.uint8:
        a = _to_rgb(a)
        return a.astype(np.float32) / 255.0 if raw else np.take(_srgb_lut8(), a.astype(np.intp))
    if mode.startswith("I;16") or a.dtype == np.uint16:
        x = _to_rgb(a.astype(np.float32) / 65535.0)
    elif mode == "F" or a.dtype.kind == "f":
        return _to_rgb(a.astype(np.float32))
    else:
        x = _to_rgb(a.astype(np.float32) / 65535.0)
    return x if raw else _srgb_decode(x)


def read_image(path: str, raw: bool = False) -> np.ndarray:
    """Read an image as linear float32 (H, W, 3). Cached by path and mtime."""
    try:
        mtime = os.path.getmtime(path)
    except OSError:
        raise SceneError("image file not found", path) from None
    key = (os.path.abspath(path), mtime, raw)
    img = _cache.get(key)
    if img is None:
        ext = os.path.splitext(path)[1].lower()
        if ext == ".exr":
            img = _read_exr(path)
        elif ext in (".hdr", ".pfm", ".rgbe"):
            raise SceneError(f"image format '{ext}' is not supported (use EXR, PNG or JPEG)", path)
        else:
            img = _read_ldr(path, raw)
        img = np.ascontiguousarray(img, dtype=np.float32)
        if img.shape[0] == 0 or img.shape[1] == 0:
            raise SceneError("image is empty", path)
        if not np.all(np.isfinite(img)):
            img = np.nan_to_num(img, nan=0.0, posinf=65504.0, neginf=0.0)
        if len(_cache) > 64:
            _cache.clear()
        _cache[key] = img
    return img
