"""mpg: unbiased, low-noise caustics from long specular chains (Manifold Path Guiding).

    scene = mpg.load_file("scene.xml", spp=64)
    img = mpg.render(scene, spp=64)
    mpg.write_exr("out.exr", img.rgb); mpg.write_png("out.png", img.rgb)
"""

from __future__ import annotations

import os as _os

# numpy's OpenBLAS threads spin-wait after each call and steal cores from the
# render threads; mpg does no large linear algebra, so one BLAS thread is enough.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from mpg.errors import MPGError, RenderError, SceneError
from mpg.image import Image, read_exr, write_exr, write_png
from mpg.render import Scene, render

__version__ = "0.1.0"


def load_file(path, substitute_missing_textures: bool = False, **params) -> Scene:
    """Load a Mitsuba 2/3 scene file; `params` override its <default> values."""
    from mpg.scene import load_file as _load

    return Scene(_load(str(path), substitute_missing_textures=substitute_missing_textures, **params))


def load_string(xml: str, base_dir=None, substitute_missing_textures: bool = False,
                **params) -> Scene:
    """Load a scene from an XML string (relative paths resolve against base_dir)."""
    from mpg.scene import load_string as _load

    return Scene(_load(xml, base_dir=None if base_dir is None else str(base_dir),
                       substitute_missing_textures=substitute_missing_textures, **params))


def default_scene_path() -> str:
    """The built-in default scene: a glass sphere casting a caustic from a small area light."""
    from importlib import resources

    return str(resources.files("mpg") / "data" / "default.xml")


__all__ = [
    "Image", "MPGError", "RenderError", "Scene", "SceneError", "default_scene_path", "load_file",
    "load_string", "read_exr", "render", "write_exr", "write_png",
]
