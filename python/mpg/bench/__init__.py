"""mpg-bench: the evaluation suite (references, equal-time comparisons, convergence
curves, cost tables). See docs/results.md for the commands and what they measure.

Modules: scenes (scene files, sidecars, content hashes), runners (integrator
entries: mpg by name, Mitsuba 3 in a subprocess), reference (cached reference
images), compare / curves / costs (the commands), report (output folders, tables,
figures), cli (argument parsing).
"""
