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
# what changed and everything downstream of it. Each file under workflow/rules/ uses
# only what the files included before it define.

import os

from snakemake.utils import min_version

min_version("9.0")


# Beside this Snakefile, so `snakemake -s /path/to/flylib/Snakefile` works from any
# directory (relative paths in the config, such as recordings, stay relative to the
# working directory).
configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/demo.smk"
include: "workflow/rules/inputs.smk"
include: "workflow/rules/pose2d.smk"
include: "workflow/rules/corrections.smk"
include: "workflow/rules/reconstruction.smk"
include: "workflow/rules/refinement.smk"
include: "workflow/rules/results.smk"
include: "workflow/rules/visualization.smk"
include: "workflow/rules/kinematics.smk"
include: "workflow/rules/neuromechfly.smk"
include: "workflow/rules/exports.smk"
include: "workflow/rules/summary.smk"


localrules:
    all,


rule all:
    default_target: True
    input:
        all_targets(),
        EXPORT_TARGETS,
