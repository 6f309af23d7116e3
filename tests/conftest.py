import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"


def shared_dir() -> pathlib.Path:
    env = os.environ.get("MPG_SHARED")
    return pathlib.Path(env) if env else ROOT.parent / "shared"


@pytest.fixture(scope="session")
def scenes_dir() -> pathlib.Path:
    return SCENES


@pytest.fixture(scope="module")
def sphere32():
    """The eval sphere at 32x32: the camera sees the small light refracted and
    reflected in the glass (the split tests)."""
    import mpg
    return mpg.load_file(SCENES / "eval" / "sphere.xml", res=32)


@pytest.fixture(scope="module")
def sphere32_path_ref(sphere32):
    """8192 spp of the path tracer on sphere32: the reference of the split tests."""
    import mpg
    return mpg.render(sphere32, "path", spp=8192, seed=31, progress=False)
