"""The stages of the pose pipeline, one home for them.

- ``flylib.pipeline.<stage>``: each stage's home, its frozen inputs object
  (:mod:`flylib.pipeline.inputs`), ``compute_<stage>`` where it has a pure step and
  ``run_<stage>`` (paths in, one artifact out), what the scripts in ``scripts/`` run;
  its record (toggle, artifact, memory...) is in :mod:`flylib.stages`;
- :mod:`flylib.pipeline.inputs`: what a stage reads, its tracked params (the rule's
  ``params.stage``) and untracked runtime;
- :mod:`flylib.pipeline.planning`: what a run plans from its config before any stage
  (its recordings, each stage's params for provenance, the config rig, and the
  workflow's ``RunPlan``: every input, param and resource its rules look up);
- :mod:`flylib.pipeline.oneshot`: :func:`run_from_points2d`, the array-in library
  one-shot of the seed API.

What each stage reads and writes:

=====================  ==========================================  ===============================
stage                  reads                                       writes
=====================  ==========================================  ===============================
``demo``               config (rig, skeleton, ``demo``)            footage, DLC CSVs, ``truth.h5``
``pose2d``             footage, or another tool's 2D files          ``stages/pose2d.h5`` (and, for
                                                                    PS, ``stages/candidates_k<k>.h5``)
``bundle_adjustment``  ``pose2d.h5``, config rig                    ``stages/bundle_adjustment.h5``
``pictorial``          ``pose2d.h5``, candidates, rig              ``stages/pictorial_structures.h5``
``triangulation``      2D (PS if on, else pose2d), rig              ``stages/triangulation.h5``
``refinement``         triangulation, pose2d, rig                   ``stages/refinement.h5``
``assemble``           the stage artifacts                          ``results.h5``, ``summary.json``,
                                                                    ``summary.png``, ``calibration.toml``,
                                                                    ``suspects.csv``
``visualization``      ``results.h5``, footage                      ``<video_name>.mp4``
``kinematics``         ``results.h5``                               ``kinematics.h5``, ``angles.csv``,
                                                                    ``angles.png``
``neuromechfly``       ``results.h5``                               ``neuromechfly.h5``,
                                                                    ``joint_angles.csv``,
                                                                    ``joint_angles.png``
=====================  ==========================================  ===============================
"""

from .oneshot import run_from_points2d

__all__ = ["run_from_points2d"]
