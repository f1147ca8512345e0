"""Tests of the Matern-5/2 kernel helpers (bams_cli.core.kernels).

The reference is GPML eq. 4.17 written out with explicit differences, never the module's code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bams_cli.core.kernels import matern52_cross_minus


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
