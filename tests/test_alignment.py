"""The similarity alignment against analytic cases (a known scale, rotation and shift)
and OpenCV's rotation."""

from __future__ import annotations

import cv2
import numpy as np

from flylib.alignment import similarity_aligned, similarity_transform


def _known(seed=0):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(40, 3))
    rot = cv2.Rodrigues(np.array([0.3, -1.1, 0.4]))[0]
    scale, shift = 1.7, np.array([2.0, -5.0, 0.5])
    return src, scale * src @ rot.T + shift, (scale, rot, shift)


def test_a_known_similarity_is_recovered_exactly():
    src, dst, (scale, rot, shift) = _known()
    got_scale, got_rot, got_shift = similarity_transform(src, dst)
    np.testing.assert_allclose(got_scale, scale, rtol=1e-12)
    np.testing.assert_allclose(got_rot, rot, atol=1e-12)
    np.testing.assert_allclose(got_shift, shift, atol=1e-12)


def test_a_mirrored_target_still_gets_a_proper_rotation():
    src, dst, _ = _known(1)
    _, rot, _ = similarity_transform(src, dst * np.array([1.0, 1.0, -1.0]))
    assert np.isclose(np.linalg.det(rot), 1.0)


def test_refits_leave_gross_errors_out():
    src, dst, (scale, rot, shift) = _known(2)
    dst[:3] += 50.0  # three gross errors in forty
    plain = similarity_transform(src, dst)
    trimmed = similarity_transform(src, dst, keep=0.9, refits=2)
    assert not np.allclose(plain[1], rot, atol=1e-3)
    np.testing.assert_allclose(trimmed[1], rot, atol=1e-9)
    np.testing.assert_allclose(trimmed[0], scale, rtol=1e-9)


def test_aligned_keeps_nan_and_needs_three_pairs():
    src, dst, _ = _known(3)
    src[5] = np.nan
    out = similarity_aligned(src, dst)
    assert np.isnan(out[5]).all()
    np.testing.assert_allclose(np.delete(out, 5, axis=0), np.delete(dst, 5, axis=0), atol=1e-10)
    assert np.isnan(similarity_aligned(src[:2], dst[:2])).all()
    assert similarity_transform(np.ones((5, 3)), dst[:5]) is None
