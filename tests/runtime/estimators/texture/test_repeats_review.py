"""Review of issue 36 (the map's repeats as texture twins): a pose whose matches are
distinctive with more repeats about it than MAX_TWINS (the twins not all judged)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ceilkit.runtime.estimators.base import AMBIGUOUS
from ceilkit.runtime.estimators.texture.estimator import MAX_TWINS

from .test_texture import _error, _on_map, _repeated


def _many_copies(office, copies: int):
    """``copies`` copies of the scatter along +x; the frame's descriptors are those of
    copy ``j`` (the last), the others' flipped (8 % of bits; the true copy 0, surveyed
    from other views, 20 %), and every copy's mosaic but the true one's and ``j``'s
    changed: the frame matches copy ``j`` distinctively, rules out every copy but the
    true one, which the mosaic explains as well as ``j``."""
    cmap, shift = _repeated(office.maps["scatter"], copies)
    rng = np.random.default_rng(5)
    n = len(cmap.descriptors) // copies
    desc = cmap.descriptors.copy()
    for k in range(copies - 1):
        p = 0.20 if k == 0 else 0.08
        desc[k * n:(k + 1) * n] ^= np.packbits(rng.random((n, 256)) < p, axis=1)
    w = cmap.mosaic.shape[1] // copies
    mosaic = cmap.mosaic.copy()
    for k in range(1, copies - 1):
        mosaic[:, k * w:(k + 1) * w] = np.flipud(mosaic[:, k * w:(k + 1) * w])
    return dataclasses.replace(cmap, descriptors=desc, mosaic=mosaic), shift


def test_a_pose_with_more_repeats_than_listed_is_not_published(office):
    """More copies than MAX_TWINS: the twins listed are not all; a pose whose twins are
    not all known must not be published valid (as the non-distinctive path refuses).
    Before: the eight listed (most support first) ruled out by the mosaic, the true
    copy (fewer alike descriptors: less support) unlisted, frame 2 published valid
    80.85 m off (copy 11)."""
    copies = MAX_TWINS + 4
    cmap, _ = _many_copies(office, copies)
    est = _on_map(office, cmap, "many.npz")
    for k in (2, 4, 6):
        truth = office.drive_poses[k]
        got = est.estimate(office.drive[k], k)
        assert not got or _error(got, truth)[0] <= 0.1, \
            (k, got.x_m - truth[0], dict(got.diagnostics))
        assert not got and got.reason == AMBIGUOUS, (k, got)
