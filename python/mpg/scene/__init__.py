"""Scene input: Mitsuba 2/3 XML -> SceneDesc (plain numpy data, world space)."""

from mpg.scene.desc import SceneDesc
from mpg.scene.loader import load_file, load_string

__all__ = ["SceneDesc", "load_file", "load_string"]
