"""The ``texture`` method's matching stages on synthetic data: the LSH index against
brute force, the two-point RANSAC and the least squares on a known pose among outliers;
and the tracked fast path's basin on the session's office scene (conftest.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ceilkit.runtime.estimators.base import PoseEstimate
from ceilkit.runtime.estimators.texture import TextureEstimator
from ceilkit.runtime.estimators.texture.match import (
    LSH_KEY_BITS,
    LSH_TABLES,
    DescriptorIndex,
    LshTables,
    _as_words,
    _lsh_keys,
    _lsh_knn,
    _rows_knn,
    key_bits,
    ransac_rigid,
    refine,
)
from ceilkit.runtime.jit import arr


def _flipped(desc: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """Each descriptor with ``bits`` of its 256 bits flipped (distinct bits)."""
    out = desc.copy()
    for row in out:
        for b in rng.choice(256, bits, replace=False):
            row[b // 8] ^= np.uint8(1 << (b % 8))
    return out


def test_index_finds_near_descriptors_within_the_distance():
    rng = np.random.default_rng(1)
    desc = rng.integers(0, 256, size=(5000, 32), dtype=np.uint8)
    index = DescriptorIndex(rng.uniform(0, 30, size=(5000, 2)), desc)
    kb = index.key_bits
    assert kb.shape == (LSH_TABLES, LSH_KEY_BITS) and len(np.unique(kb)) == kb.size
    pick = rng.choice(5000, 300, replace=False)
    query = _flipped(desc[pick], 12, rng)
    qi, mj, _ = index.match(query, 2, 64)
    found = {(int(a), int(b)) for a, b in zip(qi, mj, strict=True)}
    hit = np.mean([(k, int(j)) in found for k, j in enumerate(pick)])
    # a descriptor 12 bits off shares a table's key with p = (244/256)^16 = 0.46: some
    # table of 16 holds it with probability 1 - 0.54^16 = 0.99995
    assert hit >= 0.98, hit
    got = np.array([cv2.norm(query[a], desc[b], cv2.NORM_HAMMING)
                    for a, b in zip(qi, mj, strict=True)])
    assert np.all(got <= 64)


def _batch_knn(index: DescriptorIndex, desc: np.ndarray, rows: np.ndarray, kk: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """The reference of ``_rows_knn``: OpenCV's K nearest (``cv2.batchDistance``), as
    ``near`` and ``alike`` called it before, in map rows."""
    dist, idx = cv2.batchDistance(desc, index.descriptors[rows], -1,
                                  normType=cv2.NORM_HAMMING, K=kk)
    return np.where(idx >= 0, rows[np.maximum(idx, 0)], -1), dist


def test_rows_knn_is_opencvs_k_nearest_ties_and_all():
    """The window's and the twins' brute force (a compiled popcount) lists the same rows
    in the same order as cv2.batchDistance's K nearest: ties in the rows' order, on
    descriptors of a few values (many ties) and on random ones."""
    rng = np.random.default_rng(3)
    for trial in range(40):
        n, q = int(rng.integers(2, 300)), int(rng.integers(1, 60))
        base = rng.integers(0, 256, (3, 32), dtype=np.uint8)
        if trial % 2:
            desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
            query = rng.integers(0, 256, (q, 32), dtype=np.uint8)
        else:
            noise = (rng.random((n, 32)) < 0.03) * rng.integers(0, 256, (n, 32))
            desc = base[rng.integers(0, 3, n)] ^ noise.astype(np.uint8)
            query = base[rng.integers(0, 3, q)]
        index = DescriptorIndex(rng.uniform(0, 3, (n, 2)), desc)
        rows = rng.permutation(n)[: int(rng.integers(1, n + 1))]
        kk = int(rng.integers(1, len(rows) + 1))
        got = _rows_knn(arr(_as_words(query), np.uint64), index._words,
                        arr(rows.astype(np.int64), np.int64), kk)
        want = _batch_knn(index, query, rows, kk)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), trial


def test_key_bits_are_the_balanced_ones():
    rng = np.random.default_rng(2)
    desc = rng.integers(0, 256, size=(400, 32), dtype=np.uint8)
    desc[:, :4] = 0                      # 32 bits never set: no table may read them
    kb = key_bits(desc, tables=8, bits=16)                    # 128 of the 224 balanced
    assert kb.shape == (8, 16) and not np.any(kb < 32), kb[kb < 32]
    every = key_bits(desc)               # the default's 16 x 16 keys read each bit once
    assert sorted(every.ravel()) == list(range(256))


def test_ransac_and_refine_find_the_pose_among_outliers():
    rng = np.random.default_rng(3)
    truth = (2.0, -1.0, 0.7)
    q = rng.uniform(-1.5, 1.5, size=(60, 2))
    c, s = math.cos(truth[2]), math.sin(truth[2])
    p = q @ np.array([[c, s], [-s, c]]) + truth[:2] + rng.normal(0, 0.002, size=(60, 2))
    p[40:] = rng.uniform(-3, 3, size=(20, 2))            # a third of the matches wrong
    qi = np.arange(60)
    fit = ransac_rigid(q, p, qi, 0.01, 200, rng)
    assert fit is not None and fit.count >= 38
    ref = refine(q, p, qi, fit.pose, 0.01, 0.0005)
    assert ref is not None and len(ref.used) == 40 and set(ref.used) == set(range(40))
    assert math.hypot(ref.pose[0] - truth[0], ref.pose[1] - truth[1]) < 0.002
    assert abs(ref.pose[2] - truth[2]) < 0.002
    sd = np.sqrt(np.diag(ref.cov))
    assert 0.0002 < sd[0] < 0.002 and sd[2] < 0.003
    # the runner-up's search leaves the best's basin out: only outliers remain
    rest = np.ones(60, bool)
    rest[ref.used] = False
    other = ransac_rigid(q[rest], p[rest], qi[rest], 0.01, 200, rng, avoid=ref.pose)
    assert other is None or other.count < 6


def _prior(pose, d: float, sigma_m: float) -> PoseEstimate:
    return PoseEstimate(0, "track", pose[0] + d, pose[1] - d, pose[2] + 0.01, 0.9,
                        cov=np.diag([sigma_m ** 2, sigma_m ** 2, 0.02 ** 2]))


def test_the_fast_path_follows_from_a_prior_some_centimetres_off(office):
    """The fast path's basin: priors 1 to 7 cm off (each inside its own region, which is
    too narrow for a twin 0.3 m away) give its pose within 2 mm."""
    est = TextureEstimator(office.rig, office.sites["scatter"], {"plane_odometry": False})
    for k in (1, 3, 5):
        truth = office.drive_poses[k]
        for d, sigma in ((0.01, 0.01), (0.03, 0.02), (0.05, 0.03)):
            got = est.estimate(office.drive[k], k, _prior(truth, d, sigma))
            assert got and got.diagnostics["search"] == "tracked", (k, d, got)
            err = math.hypot(got.x_m - truth[0], got.y_m - truth[1])
            assert err < 0.002, (k, d, err)


def test_a_place_with_several_descriptors_is_weighed_against_another_place():
    """Two rows of one feature (its views' descriptors, at one point) are one place: the
    ratio test weighs the nearest against the next place, never against the feature's
    own second descriptor (which would make every such match look distinctive)."""
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, size=(1, 32), dtype=np.uint8)
    query = _flipped(a, 10, rng)
    # feature A at (1, 1) seen two ways (10 and 11 bits from the query), feature B at
    # (4, 0): 22 bits off, A is distinctive (10 <= 0.8 x 22); 12 bits off, it is not
    # (10 > 0.8 x 12), though A's own second row (11) is nearer than B
    near_a = _flipped(query, 11, rng)
    for b_bits, expected in ((22, True), (12, False)):
        b = _flipped(query, b_bits, rng)
        points = np.array([[1.0, 1.0], [1.0, 1.0], [4.0, 0.0]])
        index = DescriptorIndex(points, np.vstack([a, near_a, b]))
        for qi, mj, unique in (index.match(query, 2, 64),
                               index.near(query, (2.0, 0.0), 5.0, 2, 64)):
            assert list(qi) == [0, 0] and list(mj) == [0, 2], (qi, mj)
            assert bool(unique[0]) is expected, (b_bits, unique)


def test_the_global_search_is_the_nearest_places_among_the_bucket_sharing_rows():
    """The compiled search (one pass, its list kept by place) against the reference:
    every row sharing a bucket with the query, sorted by (distance, row), the first
    ``k`` places each at its nearest row; with places of 1 to 4 rows, their rows in
    several tables' buckets and ties of distance."""
    rng = np.random.default_rng(5)
    base = rng.integers(0, 256, size=(300, 32), dtype=np.uint8)
    owner = np.repeat(np.arange(300), rng.integers(1, 5, size=300))
    desc = _flipped(base[owner], 6, rng)
    desc[1::7] = desc[::7][: len(desc[1::7])]            # equal rows: distance ties
    index = DescriptorIndex(rng.uniform(0, 30, size=(300, 2))[owner], desc)
    query = _flipped(base[rng.choice(300, 120)], 14, rng)
    keys = _lsh_keys(query, index.key_bits)
    for k in (2, 3):
        idx, dist = _lsh_knn(query, _as_words(query),
                             LshTables(index._words, index.key_bits, index._order,
                                       index._starts), index.place, k)
        for i in range(len(query)):
            rows = np.unique(np.concatenate([
                index._order[t, index._starts[t, keys[t, i]]:index._starts[t, keys[t, i] + 1]]
                for t in range(len(keys))]))
            d = np.array([cv2.norm(query[i], desc[j], cv2.NORM_HAMMING) for j in rows], int)
            want, seen = [], set()
            for j, dj in sorted(zip(rows.tolist(), d.tolist(), strict=True),
                                key=lambda r: (r[1], r[0])):
                if index.place[j] not in seen and len(want) < k:
                    seen.add(index.place[j])
                    want.append((j, dj))
            got = [(int(j), int(dj)) for j, dj in zip(idx[i], dist[i], strict=True) if j >= 0]
            assert got == want, (k, i, got, want)
