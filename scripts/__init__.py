"""jaxnm's scripts, run from the repository root as modules (``python -m scripts.<folder>.<name>``).

- `scripts.examples`: the example scene and the example fit folder.
- `scripts.studies`: measurements of accuracy (frames, baking, speed against error, hard cases,
  maps baked by Blender).
- `scripts.benchmarks`: jaxnm beside Mitsuba 3 on one problem, and the shared timer.
"""
