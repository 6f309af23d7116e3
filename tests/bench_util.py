"""The bench/ scripts' modules for the tests that check them."""

from __future__ import annotations

import importlib
import pathlib
import sys

BENCH = str(pathlib.Path(__file__).resolve().parents[1] / "bench")


def bench_module(name: str):
    """bench/<name>.py imported as a module (bench/ on sys.path only while
    it and the bench modules it imports load)."""
    sys.path.insert(0, BENCH)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(BENCH)
