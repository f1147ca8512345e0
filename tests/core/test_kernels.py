"""Tests of the Matern-5/2 kernel helpers (bams_cli.core.kernels).

The reference is GPML eq. 4.17 written out with explicit differences, never the module's code.
"""

from __future__ import annotations

import math
import multiprocessing
import sys

import numpy as np
import pytest

from bams_cli.core import kernels
from bams_cli.core.kernels import matern52_aug_lower, matern52_cross, matern52_cross_minus


def ref_matern52(A, B, ell, s2):
    r = np.sqrt((((A[:, None, :] - B[None, :, :]) / ell) ** 2).sum(-1))
    return s2 * (1 + math.sqrt(5) * r + 5.0 / 3.0 * r**2) * np.exp(-math.sqrt(5) * r)


@pytest.mark.parametrize("d", [1, 3, 12])
def test_cross_minus_equals_dense_kernel_on_grouped_columns(d):
    rng = np.random.default_rng(d)
    A = rng.normal(size=(37, d))
    B = np.vstack([rng.normal(size=(11, d)), A[:2]])  # r = 0 entries included
    ell = rng.uniform(0.5, 2.0, size=d)
    group = rng.integers(0, len(B), size=29)
    P = rng.normal(size=(len(A), len(group)))
    want = ref_matern52(A, B[group], ell, 0.7) - P
    got = matern52_cross_minus(A, B, group, ell, 0.7, P.copy())
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)
    # k(x, x) = s2 exactly: the direct differences are exactly 0 there.
    P0 = np.zeros((2, 1))
    out = matern52_cross_minus(A[:2], B, np.array([11]), ell, 0.7, P0)
    assert out[0, 0] == 0.7


def test_cross_minus_rejects_mismatched_shapes():
    A, B = np.zeros((3, 2)), np.zeros((4, 2))
    with pytest.raises(ValueError, match="C-contiguous of shape"):
        matern52_cross_minus(A, B, np.array([0, 1]), np.ones(2), 1.0, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="index the rows"):
        matern52_cross_minus(A, B, np.array([0, 4]), np.ones(2), 1.0, np.zeros((3, 2)))


@pytest.mark.parametrize("d", [1, 12])
def test_cross_equals_dense_kernel(d):
    rng = np.random.default_rng(100 + d)
    A = rng.normal(size=(41, d))
    B = np.vstack([rng.normal(size=(23, d)), A[:3]])
    ell = rng.uniform(0.5, 3.0, size=d)
    got = matern52_cross(A, B, ell, 1.3)
    assert got.flags.c_contiguous and got.shape == (41, 26)
    np.testing.assert_allclose(got, ref_matern52(A, B, ell, 1.3), rtol=1e-13, atol=1e-15)
    assert np.all(got[np.arange(3), 23 + np.arange(3)] == 1.3)  # r = 0: exactly s2


def ref_aug(X, levels, ell, s):
    """k0 + [l_i == l_j >= 1] k_l, dense, from GPML eq. 4.17 (paper sec. 3)."""
    K = ref_matern52(X, X, ell[0], s[0])
    for lv in range(1, len(s)):
        same = (levels[:, None] == lv) & (levels[None, :] == lv)
        K += same * ref_matern52(X, X, ell[lv], s[lv])
    return K


@pytest.mark.parametrize(("n", "n_levels"), [(1, 1), (2, 2), (30, 3), (31, 2)])
def test_aug_lower_fills_the_lower_triangle_of_the_multifidelity_covariance(n, n_levels):
    rng = np.random.default_rng(n)
    d = 4
    X = rng.normal(size=(n, d))
    X[-1] = X[0]  # a repeated site (same level or not)
    levels = rng.integers(0, n_levels, size=n)
    ell = rng.uniform(0.5, 3.0, size=(n_levels, d))
    s = rng.uniform(0.2, 2.0, size=n_levels)
    K = np.full((n, n), 7.0, order="F")
    out = matern52_aug_lower(X, levels, ell, s, K)
    assert out is K
    lower = np.tril_indices(n)
    np.testing.assert_allclose(K[lower], ref_aug(X, levels, ell, s)[lower], rtol=1e-13)
    assert np.all(K[np.triu_indices(n, 1)] == 7.0)  # the strict upper triangle untouched
    np.testing.assert_array_equal(np.diag(K), s[0] + np.where(levels >= 1, s[levels], 0.0))


def test_aug_lower_needs_a_fortran_float64_square():
    X, lv = np.zeros((3, 2)), np.zeros(3, np.int64)
    for K in (np.zeros((3, 3)), np.zeros((3, 2), order="F"), np.zeros((3, 3), np.float32, "F")):
        with pytest.raises(ValueError, match="Fortran-contiguous float64"):
            matern52_aug_lower(X, lv, np.ones((1, 2)), np.ones(1), K)


@pytest.mark.parametrize("threads", [2, 3, 7])
def test_rows_split_over_threads_give_the_one_thread_result_bit_for_bit(threads, monkeypatch):
    rng = np.random.default_rng(threads)
    A, B = rng.normal(size=(1001, 5)), rng.normal(size=(433, 5))
    ell = rng.uniform(0.5, 2.0, size=5)
    group = rng.integers(0, len(B), size=700)
    P = rng.normal(size=(len(A), len(group)))
    assert len(A) * len(B) >= kernels._THREADED_FROM  # the threaded path runs
    monkeypatch.setattr(kernels, "_THREADS", 1)
    one = matern52_cross(A, B, ell, 0.9), matern52_cross_minus(A, B, group, ell, 0.9, P.copy())
    monkeypatch.setattr(kernels, "_THREADS", threads)
    calls = []
    real = kernels._matern52_cross
    monkeypatch.setattr(
        kernels, "_matern52_cross", lambda lo, hi, *a: (calls.append((lo, hi)), real(lo, hi, *a))
    )
    many = matern52_cross(A, B, ell, 0.9), matern52_cross_minus(A, B, group, ell, 0.9, P.copy())
    calls.sort()  # threads append in whatever order they run
    assert len(calls) == threads and calls[0][0] == 0 and calls[-1][1] == len(A)
    assert all(a[1] == b[0] and a[0] < a[1] for a, b in zip(calls[:-1], calls[1:], strict=True))
    for got, want in zip(many, one, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(one[0], ref_matern52(A, B, ell, 0.9), rtol=1e-13, atol=1e-15)


def _cross_sum(A):
    return float(matern52_cross(A, A, np.ones(A.shape[1]), 1.0).sum())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork is Linux's default")
def test_a_process_that_used_the_kernels_can_fork_workers_that_use_them():
    """select loads the posterior (both kernels run), then forks its cluster workers, which
    score again. Threaded numba kernels (GNU OpenMP) kill such a worker at its first call."""
    from concurrent.futures import ProcessPoolExecutor

    A = np.random.default_rng(0).normal(size=(600, 3))  # 360,000 entries: on threads
    assert len(A) ** 2 >= kernels._THREADED_FROM
    K = np.zeros((600, 600), order="F")
    matern52_aug_lower(A, np.zeros(600, np.int64), np.ones((1, 3)), np.ones(1), K)
    want = _cross_sum(A)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
        assert list(pool.map(_cross_sum, [A, A])) == [want, want]
