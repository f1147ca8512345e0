"""Tests of Algorithm 2 (bams_cli.core.cluster)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from bams_cli.core.cluster import cluster_pool, hausdorff, merge_smallest


def _hausdorff_brute(A, B):
    D = cdist(A, B)
    return max(D.min(axis=1).max(), D.min(axis=0).max())


def _merge_brute(Z, labels, S):
    """Algorithm 2 lines 2-6 with full pairwise distance matrices."""
    clusters = {int(k): list(np.flatnonzero(labels == k)) for k in np.unique(labels)}
    while len(clusters) > S:
        s = min(clusters, key=lambda k: (len(clusters[k]), k))
        dists = {k: _hausdorff_brute(Z[clusters[s]], Z[clusters[k]]) for k in clusters if k != s}
        j = min(dists, key=lambda k: (dists[k], k))
        clusters[j] += clusters.pop(s)
    return sorted(sorted(v) for v in clusters.values())


@pytest.mark.parametrize("seed", range(5))
def test_hausdorff_matches_pairwise(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(70, 3))
    B = rng.normal(loc=0.5, size=(45, 3))
    assert hausdorff(A, B) == pytest.approx(_hausdorff_brute(A, B), rel=1e-14)
    assert hausdorff(A, A) == 0.0


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("S", [1, 2, 4])
def test_merges_match_brute_force(seed, S):
    rng = np.random.default_rng(seed)
    # Uneven blobs so that "smallest" and "nearest" are both exercised.
    sizes = rng.integers(3, 40, size=8)
    centres = rng.normal(scale=4.0, size=(8, 2))
    Z = np.vstack([c + rng.normal(size=(n, 2)) for c, n in zip(centres, sizes, strict=True)])
    labels = np.repeat(np.arange(8), sizes)
    perm = rng.permutation(len(Z))
    Z, labels = Z[perm], labels[perm]
    got = merge_smallest(Z, labels, S)
    assert sorted(np.unique(got).tolist()) == list(range(S))
    got_sets = sorted(sorted(np.flatnonzero(got == k).tolist()) for k in range(S))
    assert got_sets == _merge_brute(Z, labels, S)
    # numbered in order of each cluster's lowest point index
    firsts = [np.flatnonzero(got == k)[0] for k in range(S)]
    assert firsts == sorted(firsts)


@pytest.mark.parametrize("S", [1, 3, 6])
def test_cluster_pool_gives_exactly_S_clusters(S):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(600, 4))
    ell = np.array([1.0, 2.0, 0.5, 3.0])
    labels = cluster_pool(X, ell, S, rng=np.random.default_rng(1))
    assert labels.shape == (600,)
    assert sorted(np.unique(labels).tolist()) == list(range(S))
    if S == 1:
        assert np.all(labels == 0)
    again = cluster_pool(X, ell, S, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(labels, again)


def test_cluster_pool_uses_lengthscales():
    # Two groups separated along dim 0 only; a huge lengthscale on dim 0 hides the split,
    # so K-means then cuts along dim 1 instead.
    rng = np.random.default_rng(0)
    X = np.column_stack([np.r_[np.zeros(100), np.full(100, 10.0)], rng.uniform(0, 1, 200)])
    X[:, 0] += rng.normal(scale=0.1, size=200)
    split = cluster_pool(
        X, np.array([1.0, 1.0]), 2, n_init_clusters=2, rng=np.random.default_rng(0)
    )
    assert len(np.unique(split[:100])) == 1 and split[0] != split[150]
    hidden = cluster_pool(
        X, np.array([1e6, 1.0]), 2, n_init_clusters=2, rng=np.random.default_rng(0)
    )
    assert len(np.unique(hidden[:100])) == 2


def test_cluster_pool_small_and_bad_inputs():
    X = np.random.default_rng(0).normal(size=(5, 2))
    labels = cluster_pool(X, np.ones(2), 8, rng=np.random.default_rng(0))
    assert len(np.unique(labels)) == 5  # never more clusters than points
    with pytest.raises(ValueError, match="n_init_clusters"):
        cluster_pool(X, np.ones(2), 3, n_init_clusters=2, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="n_clusters"):
        cluster_pool(X, np.ones(2), 0, rng=np.random.default_rng(0))


# Ties. Points on a line, listed so that the label order and the point order disagree (a
# tie broken by "first point" or by "highest label" gives the other answer).
def test_tie_for_smallest_goes_to_the_lowest_label():
    # Labels 1 ({20}) and 3 ({0}) are both the smallest. Label 1 merges, into label 2
    # ({21, 22, 23}, 3 away); merging label 3 instead would join {0} to {1, 2, 3}.
    Z = np.array([0.0, 1, 2, 3, 20, 21, 22, 23])[:, None]
    labels = np.array([3, 0, 0, 0, 1, 2, 2, 2])
    got = merge_smallest(Z, labels, 3)
    np.testing.assert_array_equal(got, [0, 1, 1, 1, 2, 2, 2, 2])  # {0} {1,2,3} {20..23}


def test_tie_for_nearest_goes_to_the_lowest_label():
    # {0} (label 1) is exactly 3 from both {2, 3} (label 0) and {-2, -3} (label 2): it joins
    # label 0; joining label 2 would give {-3, -2, 0} and {2, 3}.
    Z = np.array([-2.0, -3, 0, 2, 3])[:, None]
    labels = np.array([2, 2, 1, 0, 0])
    assert hausdorff(Z[2:3], Z[3:]) == hausdorff(Z[2:3], Z[:2]) == 3.0
    got = merge_smallest(Z, labels, 2)
    np.testing.assert_array_equal(got, [0, 0, 1, 1, 1])  # {-2, -3} {0, 2, 3}


def test_cluster_pool_on_a_sample_labels_every_point_like_its_nearest_centre():
    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    X = np.vstack([c + rng.standard_normal((500, 2)) for c in centres])
    ell = np.ones(2)
    full = cluster_pool(X, ell, 4, rng=np.random.default_rng(0))
    same = cluster_pool(X, ell, 4, rng=np.random.default_rng(0), fit_max=len(X))
    np.testing.assert_array_equal(full, same)  # fit_max >= n: the whole pool, as before
    sampled = cluster_pool(X, ell, 4, rng=np.random.default_rng(0), fit_max=300)
    assert sorted(np.unique(sampled)) == [0, 1, 2, 3]
    _, first = np.unique(sampled, return_index=True)
    assert np.all(np.diff(first) > 0)  # numbered by each cluster's lowest point index
    for k in range(4):  # well-separated blobs: each blob is one cluster either way
        assert len(np.unique(sampled[500 * k : 500 * (k + 1)])) == 1
