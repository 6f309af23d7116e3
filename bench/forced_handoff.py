"""Run another bench script with two extra `mpg` parameters that override the
maps mpg learned, in its final render only (the training is unchanged):

  force_k=K      every pixel handed to the path tracer (rate 0) with K guided
                 traces each (0: none), in place of the learned rates and
                 trace counts;
  trace_all_k=K  the learned rates, but K guided traces in every handed pixel.

A measurement tool for the learned maps' choice (docs/results.md,
thirty-third session, "Handing every pixel off"). The renderer's option
`handoff_all=K` (thirty-fourth session) does what force_k does, but before
the pixel split, the traces' map and the photon pilot, which then see the
handed maps; force_k replaces the maps of the final render call only:

    python bench/forced_handoff.py bench/ab_params.py double_slabs --time 2 --seeds 16 \\
        --variants '{}' '{"force_k": 4}' '{"force_k": 2}'
    python bench/forced_handoff.py bench/error_classes.py double_slabs \\
        --integrator mpg/force_k=2 --time 10 --seeds 3

Any parameter or integrator string of the wrapped script may carry them."""

from __future__ import annotations

import pathlib
import runpy
import sys

import numpy as np

import mpg  # noqa: F401  (mpg.render the module, below)

R = sys.modules["mpg.render"]
EXTRA = {"force_k", "trace_all_k"}
_force: dict[str, int] = {}
_resolve = R._resolve_integrator
_render = R.render


def _resolve_forced(scene, integrator):
    name, params, warnings = _resolve(scene, integrator)
    if EXTRA & params.keys():
        _force.clear()
        for k in EXTRA & params.keys():
            _force[k] = int(float(params.pop(k)))
    elif name == "mpg" and "guide" not in params:
        _force.clear()   # (a top-level mpg render without them)
    return name, params, warnings


def _render_forced(scene, integrator=None, **kw):
    # (mpg's final render is the one call with a rate map)
    q = kw.get("chain_rate_map")
    if q is not None and "force_k" in _force:
        kw["chain_rate_map"] = np.zeros_like(q)
        kw["guided_trace_map"] = np.full(q.shape, float(_force["force_k"]), dtype=np.float32)
    elif q is not None and "trace_all_k" in _force:
        kw["guided_trace_map"] = np.full(q.shape, float(_force["trace_all_k"]), dtype=np.float32)
    return _render(scene, integrator=integrator, **kw)


def main() -> None:
    if len(sys.argv) < 2 or not pathlib.Path(sys.argv[1]).is_file():
        sys.exit(__doc__)
    R.KNOWN_PARAMS = R.KNOWN_PARAMS | EXTRA
    R.GUIDE_PARAMS = R.GUIDE_PARAMS | EXTRA
    R._resolve_integrator = _resolve_forced
    R.render = _render_forced   # (guiding.render_mpg imports it at call time)
    script = sys.argv[1]
    sys.path.insert(0, str(pathlib.Path(script).resolve().parent))
    sys.argv = [script] + sys.argv[2:]
    runpy.run_path(script, run_name="__main__")


if __name__ == "__main__":
    main()
