# flylib: markerless 3D pose estimation of tethered Drosophila from a 7-camera rig.
#
#   snakemake --cores 2                      # the recordings listed in config/config.yaml
#   snakemake --cores 2 --configfile my.yaml # another config
#   snakemake --profile profiles/slurm       # on a SLURM cluster
#   snakemake --report demo/flylib_outputs/report.html  # HTML report (figures, videos);
#                                            # put it beside your outputs, not in the checkout
#
# Each rule runs one thin command script from scripts/ through `script:` (each is also
# runnable by hand, see --help) and writes one artifact; a rule's `params` is exactly the config subset that
# affects its result, so after editing the config a plain re-run recomputes only
# what changed and everything downstream of it.

import os
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


# Beside this Snakefile, so `snakemake -s /path/to/flylib/Snakefile` works from any
# directory (relative paths in the config, such as recordings, stay relative to the
# working directory).
configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


# In order: each file uses only what the files before it define. A stage added since (its
# home flylib/pipeline/<stage>.py and its rule file) is included after them.
RULE_FILES = [
    "common.smk",
    "demo.smk",
    "inputs.smk",
    "pose2d.smk",
    "corrections.smk",
    "reconstruction.smk",
    "refinement.smk",
    "results.smk",
    "visualization.smk",
    "kinematics.smk",
    "neuromechfly.smk",
    "exports.smk",
    "summary.smk",
]
_added = Path(workflow.basedir, "workflow", "rules").glob("*.smk")
RULE_FILES += sorted(p.name for p in _added if p.name not in RULE_FILES)
for _name in RULE_FILES:

    include: f"workflow/rules/{_name}"


localrules:
    all,


rule all:
    default_target: True
    input:
        all_targets(),
        EXPORT_TARGETS,
