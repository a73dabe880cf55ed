"""Stage functions called directly (what the workflow's scripts run)."""

from __future__ import annotations

import pytest

from flylib.config import Config
from flylib.errors import ResultsError
from flylib.pipeline.demo import demo_import_spec, make_demo
from flylib.pipeline.inputs import stage_inputs
from flylib.pipeline.pictorial_structures import run_pictorial_structures
from flylib.pipeline.pose2d import run_pose2d
from flylib.pipeline.stage_helpers import run_inputs
from flylib.pipeline.triangulation import run_triangulation


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """A tiny recording whose 2D is imported from DeepLabCut CSVs, and its pose2d artifact."""
    root = tmp_path_factory.mktemp("stages")
    config = Config.default()
    make_demo(config, root / "rec", frames=4, seed=0)
    spec = demo_import_spec(config)
    pose2d = run_pose2d(
        stage_inputs(config, "pose2d"), root / "rec", root / "pose2d.h5", import_spec=spec
    )
    return config, root, spec, pose2d


def test_candidates_for_imported_2d_fail_in_one_line_with_the_fix(imported):
    config, root, spec, _ = imported
    with pytest.raises(
        ResultsError,
        match=r"rec: pictorial structures needs the detector's "
        r"candidate peaks.*imported \(dlc_csv\).*do_pictorial_structures: false",
    ):
        run_pose2d(
            stage_inputs(config, "pose2d"),
            root / "rec",
            root / "other.h5",
            import_spec=spec,
            candidates_path=root / "candidates.h5",
        )
    assert not (root / "other.h5").exists() and not (root / "candidates.h5").exists()


def test_pictorial_structures_without_candidates_names_the_artifact(imported):
    config, root, _, pose2d = imported
    inputs = run_inputs(config, "pictorial_structures")
    with pytest.raises(ResultsError, match=r"pose2d.h5: holds no candidate peaks"):
        run_pictorial_structures(inputs, pose2d, root / "ps.h5")
    with pytest.raises(ResultsError, match=r"absent.h5"):
        run_pictorial_structures(inputs, pose2d, root / "ps.h5", candidates_path=root / "absent.h5")
    assert not (root / "ps.h5").exists()


def test_a_rig_stage_with_bundle_adjustment_on_needs_its_artifact(imported):
    config, root, _, pose2d = imported
    inputs = stage_inputs(config, "triangulation")
    assert inputs.rig is None  # bundle adjustment on: the rig comes from its artifact
    with pytest.raises(ResultsError, match=r"^triangulation: bundle adjustment is on.*--bundle"):
        run_triangulation(inputs, pose2d, root / "tri.h5")
    assert not (root / "tri.h5").exists()
    # without the artifact a run uses the config rig, and its params track that rig
    out = run_triangulation(run_inputs(config, "triangulation"), pose2d, root / "tri.h5")
    assert out.exists() and run_inputs(config, "triangulation").rig is not None
