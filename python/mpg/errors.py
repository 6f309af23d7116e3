"""Exceptions with messages a user can act on."""

from __future__ import annotations


class MPGError(Exception):
    """Base class of every error mpg raises on purpose."""


class SceneError(MPGError):
    """Bad scene input. The message names the file, the line and the problem."""

    def __init__(self, message: str, file: str | None = None, line: int | None = None):
        self.file = file
        self.line = line
        self.problem = message
        where = ""
        if file is not None:
            where = f"{file}:{line}: " if line is not None else f"{file}: "
        super().__init__(where + message)


class RenderError(MPGError):
    """A render could not run (bad parameters, invalid integrator...)."""
