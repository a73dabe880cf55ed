"""The stages of the pose pipeline, one home for them.

- :mod:`flylib.pipeline.stages`: one function per workflow stage (paths in, one
  artifact out), what the scripts in ``scripts/`` run;
- :mod:`flylib.pipeline.tracked`: the config a stage may read (exactly what its rule
  tracks);
- :mod:`flylib.pipeline.planning`: what a run plans from its config before any stage
  (its recordings, each stage's params for provenance, the config rig);
- :mod:`flylib.pipeline.artifacts`: the names of the files the workflow writes;
- :mod:`flylib.pipeline.oneshot`: :func:`run_from_points2d`, the array-in library
  one-shot of the seed API.
"""

from .oneshot import run_from_points2d

__all__ = ["run_from_points2d"]
