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
