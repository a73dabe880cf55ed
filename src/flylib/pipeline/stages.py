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

from .assemble import run_assemble, write_snapshot
from .bundle_adjustment import run_bundle_adjustment
from .demo import run_demo
from .kinematics import run_kinematics
from .neuromechfly import run_neuromechfly
from .pictorial_structures import run_pictorial_structures
from .pose2d import run_pose2d
from .refinement import run_refinement
from .stage_helpers import run_inputs
from .triangulation import run_triangulation
from .visualization import run_visualization

__all__ = [
    "run_assemble",
    "run_bundle_adjustment",
    "run_demo",
    "run_inputs",
    "run_kinematics",
    "run_neuromechfly",
    "run_pictorial_structures",
    "run_pose2d",
    "run_refinement",
    "run_triangulation",
    "run_visualization",
    "write_snapshot",
]
