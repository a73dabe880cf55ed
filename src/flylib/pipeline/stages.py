"""Every workflow stage's function, importable from one place.

Each stage has one home, ``flylib.pipeline.<stage>``: its frozen inputs object
(:mod:`flylib.pipeline.inputs`), ``compute_<stage>`` where it has a pure step (arrays
and inputs in, a result object out) and ``run_<stage>(inputs, paths...)``, which loads
the upstream artifact(s), computes and writes the stage's artifact atomically. These are
what the command scripts in ``scripts/`` (and so the Snakemake rules) run, and what a
library user calls to reproduce one step by hand; none decides *whether* it should run
(the workflow does, from the rule's params and inputs).

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

from importlib import import_module

#: ``name -> the module (under flylib.pipeline) that defines it``; imported on first use,
#: so a job that runs one stage does not import every stage's libraries (JAX, torch).
_HOMES = {
    "run_assemble": "assemble",
    "write_snapshot": "assemble",
    "run_bundle_adjustment": "bundle_adjustment",
    "run_demo": "demo",
    "run_kinematics": "kinematics",
    "run_neuromechfly": "neuromechfly",
    "run_pictorial_structures": "pictorial_structures",
    "run_pose2d": "pose2d",
    "run_refinement": "refinement",
    "run_inputs": "stage_helpers",
    "run_triangulation": "triangulation",
    "run_visualization": "visualization",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(import_module(f"{__package__}.{_HOMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
