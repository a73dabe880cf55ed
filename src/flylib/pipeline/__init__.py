"""The stages of the pose pipeline, one module each.

- ``flylib.pipeline.<stage>``: its record (``RECORD``, a :class:`flylib.stages.Stage`), its
  inputs object, ``compute_<stage>`` (the pure step, where there is one) and ``run_<stage>``
  (paths in, one artifact out; what ``scripts/`` run);
- :mod:`flylib.pipeline.inputs`: what a stage reads, its tracked params and untracked runtime;
- :mod:`flylib.pipeline.planning`: what a run plans from its config before any stage;
- :mod:`flylib.pipeline.oneshot`: :func:`run_from_points2d`, the array-in one-shot.

What each stage reads -> writes (``stages/`` under the output folder):

- ``demo``: config (rig, skeleton, ``demo``) -> footage, DLC CSVs, ``truth.h5``
- ``pose2d``: footage or another tool's 2D -> ``pose2d.h5`` (PS: ``candidates_k<k>.h5``)
- ``bundle_adjustment``: ``pose2d.h5``, config rig -> ``bundle_adjustment.h5``
- ``pictorial``: ``pose2d.h5``, candidates, rig -> ``pictorial_structures.h5``
- ``triangulation``: 2D (PS if on, else pose2d), rig -> ``triangulation.h5``
- ``refinement``: triangulation, pose2d, rig -> ``refinement.h5``
- ``assemble``: the stage artifacts -> ``results.h5``, ``summary.json``, ``summary.png``,
  ``calibration.toml``, ``suspects.csv``
- ``visualization``: ``results.h5``, footage -> ``<video_name>.mp4``
- ``kinematics``: ``results.h5`` -> ``kinematics.h5``, ``angles.csv``, ``angles.png``
- ``neuromechfly``: ``results.h5`` -> ``neuromechfly.h5``, ``joint_angles.{csv,png}``
"""

from .oneshot import run_from_points2d

__all__ = ["run_from_points2d"]
