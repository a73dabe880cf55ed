"""Detector weights are checked on every use.

No SHA-256 of the published DeepFly2D checkpoint is published or could be established
(DeepFly2D/DeepFly3D's sources download it without one; the spec lists its layout, not
its bytes), so none is pinned: the first download's hash is recorded beside the file
and every later use is checked against it; a hash given in the config is checked on
download and on every use. The "published" file here is a small checkpoint served
from a ``file://`` URL, the way ``urllib`` fetches the real one.
"""

from __future__ import annotations

import logging
import zipfile
from types import SimpleNamespace

import pytest
import torch

from flylib.errors import WeightsError
from flylib.paths import cache_dir
from flylib.pose2d import weights
from flylib.pose2d.model import HourglassNet


@pytest.fixture
def published(tmp_path, monkeypatch):
    monkeypatch.setenv("FLYLIB_CACHE", str(tmp_path / "cache"))
    net = HourglassNet(num_stacks=1, num_blocks=1, num_classes=3, inplanes=8, num_feats=8)
    return weights.save_checkpoint(net, tmp_path / "published" / "sh8_front_j8.tar")


def _flip_a_byte(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def test_no_sha256_is_pinned_for_the_published_weights():
    """Honest: none is known, so none is invented (see the module docstring)."""
    assert weights.PUBLISHED_WEIGHTS["hourglass"]["sha256"] is None


def test_first_download_records_its_hash_and_later_uses_check_it(published, caplog):
    with caplog.at_level(logging.WARNING, logger="flylib.pose2d.weights"):
        path = weights.resolve_weights("", url=published.as_uri())
    record = weights.recorded_sha256_path(path)
    digest = weights.sha256sum(published)
    assert record.read_text() == f"{digest}  {path.name}\n"
    assert "trust on first use" in caplog.text and digest in caplog.text
    assert weights.resolve_weights("", url="http://127.0.0.1:9/offline.tar") == path
    _flip_a_byte(path)
    with pytest.raises(WeightsError) as err:
        weights.resolve_weights("", url="http://127.0.0.1:9/offline.tar")
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{path}: ")
    assert "changed since it was downloaded" in text and f"recorded {digest}" in text
    assert "delete both files" in text


def test_a_file_put_in_the_cache_by_hand_is_recorded_then_checked(published, caplog):
    cached = cache_dir() / "sh8_deepfly.tar"
    cached.parent.mkdir(parents=True)
    cached.write_bytes(published.read_bytes())
    with caplog.at_level(logging.WARNING, logger="flylib.pose2d.weights"):
        assert weights.resolve_weights("", allow_download=False) == cached
    assert "recorded its hash" in caplog.text
    assert weights.recorded_sha256_path(cached).is_file()
    _flip_a_byte(cached)
    with pytest.raises(WeightsError, match="changed since it was downloaded"):
        weights.resolve_weights("", allow_download=False)


def test_a_new_download_replaces_a_stale_record(published):
    cached = cache_dir() / "sh8_deepfly.tar"
    cached.parent.mkdir(parents=True)
    weights.recorded_sha256_path(cached).write_text(f"{'0' * 64}  sh8_deepfly.tar\n")
    path = weights.resolve_weights("", url=published.as_uri())
    assert weights.recorded_sha256_path(path).read_text().split()[0] == weights.sha256sum(path)


def test_a_damaged_record_is_one_line_naming_it(published):
    path = weights.resolve_weights("", url=published.as_uri())
    record = weights.recorded_sha256_path(path)
    record.write_text("not a hash\n")
    with pytest.raises(WeightsError, match=f"^{record}: not a SHA-256 record"):
        weights.resolve_weights("", allow_download=False)


def test_a_given_sha256_is_checked_on_download_and_on_every_use(published, tmp_path):
    digest = weights.sha256sum(published)
    with pytest.raises(WeightsError, match="checksum mismatch"):
        weights.resolve_weights("", url=published.as_uri(), sha256="0" * 64)
    path = weights.resolve_weights("", url=published.as_uri(), sha256=digest)
    assert not weights.recorded_sha256_path(path).exists()  # the pinned hash is the record
    _flip_a_byte(path)
    with pytest.raises(WeightsError, match=f"^{path}: checksum mismatch"):
        weights.resolve_weights("", sha256=digest, allow_download=False)
    own = tmp_path / "mine.tar"
    own.write_bytes(published.read_bytes())
    assert weights.resolve_weights(own, sha256=digest) == own
    with pytest.raises(WeightsError, match="checksum mismatch"):
        weights.resolve_weights(own, sha256="f" * 64)


def test_a_file_that_torch_save_did_not_write_is_told_from_its_layout_alone(tmp_path):
    """Validation refuses a junk weights file before any job, without unpickling it;
    every layout torch.save writes passes (issue 36, 9)."""
    from flylib.pose2d.published import checkpoint_problem, container_problem

    state = {"state_dict": {"module.conv1.weight": torch.ones(2)}}
    torch.save(state, tmp_path / "zip.tar")
    torch.save(state, tmp_path / "legacy.tar", _use_new_zipfile_serialization=False)
    assert container_problem(tmp_path / "zip.tar") is None
    assert container_problem(tmp_path / "legacy.tar") is None
    (tmp_path / "junk.tar").write_text("not a checkpoint\n")
    (tmp_path / "empty.tar").write_bytes(b"")
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("readme.txt", "hello")
    assert container_problem(tmp_path / "junk.tar") == (
        "neither a torch.save zip archive nor torch's legacy format"
    )
    assert container_problem(tmp_path / "empty.tar") == "empty"
    assert container_problem(tmp_path / "other.zip") == "a zip archive without torch's data.pkl"
    spec = SimpleNamespace(
        name="deepfly2d", model_class="hourglass", weights=str(tmp_path / "junk.tar"), url=None
    )
    assert checkpoint_problem(spec, "pose2d.weights.deepfly2d") == (
        f"pose2d.weights.deepfly2d: {tmp_path / 'junk.tar'} is not a PyTorch checkpoint "
        "(neither a torch.save zip archive nor torch's legacy format); point it at the model's "
        "checkpoint (a torch.save file holding {'state_dict': ...}, such as DeepFly2D's sh8 .tar)"
    )
