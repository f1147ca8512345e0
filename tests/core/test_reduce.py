"""Exact streaming PCA (core/reduce.py) against scikit-learn's batch PCA."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.decomposition import PCA

from bams_cli.core.reduce import (
    Reducer,
    Scatter,
    fit_reducer,
    null_components,
    pca_from_covariance,
)

N, D, DIM = 5_000, 64, 12


def _data(offset: float = 0.0, seed: int = 0) -> np.ndarray:
    """N x D rows with covariance Q diag(lambda) Q^T, lambda from 1 down to 1e-3.

    Consecutive eigenvalues differ by 12 %, far above the sampling noise sqrt(2 / N) = 2 %,
    so the leading DIM eigenvectors are well determined (an error of eps in the covariance
    moves them by ~ eps / gap).
    """
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(D, D)))
    lam = 10 ** np.linspace(0, -3, D)
    return (rng.normal(size=(N, D)) * np.sqrt(lam)) @ Q.T + offset


def _chunks(X: np.ndarray, size: int):
    return lambda: (X[i : i + size] for i in range(0, len(X), size))


def _naive_covariance(X: np.ndarray, size: int) -> np.ndarray:
    """Textbook one-pass accumulation: (sum x x^T - n mean mean^T) / (n - 1)."""
    S, s = np.zeros((D, D)), np.zeros(D)
    for B in _chunks(X, size)():
        S += B.T @ B
        s += B.sum(axis=0)
    m = s / len(X)
    return (S - len(X) * np.outer(m, m)) / (len(X) - 1)


def _streaming_covariance(X: np.ndarray, size: int) -> np.ndarray:
    acc = Scatter()
    for B in _chunks(X, size)():
        acc.update(B)
    assert acc.n == len(X)
    return acc.covariance()


def _assert_matches_sklearn(components, explained, ref: PCA) -> None:
    # sklearn fixes signs its own way; compare up to one sign per component.
    sign = np.sign(np.sum(components * ref.components_, axis=1))
    np.testing.assert_allclose(components, sign[:, None] * ref.components_, rtol=0, atol=1e-6)
    np.testing.assert_allclose(explained, ref.explained_variance_, rtol=1e-8)


@pytest.mark.parametrize("offset", [0.0, 1e4])
@pytest.mark.parametrize("size", [N, 997, 7])
def test_streaming_covariance_gives_sklearns_pca(offset, size):
    X = _data(offset)
    ref = PCA(DIM, svd_solver="full").fit(X)
    components, explained = pca_from_covariance(_streaming_covariance(X, size), DIM)
    _assert_matches_sklearn(components, explained, ref)
    np.testing.assert_allclose(_streaming_covariance(X, size), np.cov(X.T), rtol=0, atol=1e-12)


@pytest.mark.parametrize("size", [N, 997, 7])
def test_naive_accumulation_fails_the_same_test_under_an_offset(size):
    """The test above has teeth: sum-of-squares accumulation loses ~8 digits at 1e4 + N(0, 1),
    and the sub-unit eigenvalues then miss 1e-8 by a factor of 20 or more."""
    X = _data(1e4)
    ref = PCA(DIM, svd_solver="full").fit(X)
    # without the offset the naive form is fine: the failure is cancellation, not the test
    _assert_matches_sklearn(*pca_from_covariance(_naive_covariance(X - 1e4, size), DIM), ref)
    components, explained = pca_from_covariance(_naive_covariance(X, size), DIM)
    assert np.max(np.abs(explained / ref.explained_variance_ - 1)) > 1e-7
    with pytest.raises(AssertionError):
        _assert_matches_sklearn(components, explained, ref)


@pytest.mark.parametrize("standardize", [False, True])
@pytest.mark.parametrize(("offset", "size"), [(0.0, 8192), (1e4, 333)])
def test_fit_reducer_transforms_like_sklearn(standardize, offset, size):
    X = _data(offset, seed=1)
    scale = X.std(axis=0, ddof=1) if standardize else np.ones(D)
    S = X / scale  # sklearn centres; scaling first is the same standardisation
    ref = PCA(DIM, svd_solver="full").fit(S)
    calls = []

    def batches():
        calls.append(1)
        return _chunks(X, size)()

    r = fit_reducer(batches, method="pca", dim=DIM, standardize=standardize, rng=None)  # type: ignore[arg-type]
    assert len(calls) == 1  # one pass over the data
    np.testing.assert_allclose(r.scale, scale, rtol=1e-10)
    np.testing.assert_allclose(r.mean, X.mean(axis=0), rtol=1e-12, atol=1e-12)
    _assert_matches_sklearn(r.weights[0].T, r.explained_variance, ref)
    Z, Zref = r.transform(X), ref.transform(S)
    sign = np.sign(np.sum(Z * Zref, axis=0))
    np.testing.assert_allclose(Z, sign * Zref, rtol=0, atol=1e-8 * np.abs(Zref).max())
    # Its reported error is the pool's mean squared residual per coordinate, exactly.
    Sc = (X - r.mean) / r.scale
    residual = Sc - Z @ r.weights[0].T
    assert r.reconstruction_error["pca"] == pytest.approx(np.mean(residual**2), rel=1e-8)


def test_sign_is_fixed_by_the_largest_loading_and_reruns_are_identical():
    X = _data(1e4, seed=2)

    def fit(size: int) -> Reducer:
        return fit_reducer(_chunks(X, size), method="pca", dim=DIM, rng=None)  # type: ignore[arg-type]

    a, b, c = fit(500), fit(500), fit(61)
    np.testing.assert_array_equal(a.transform(X), b.transform(X))
    W = a.weights[0]
    lead = np.argmax(np.abs(W), axis=0)
    assert np.all(W[lead, np.arange(DIM)] > 0)
    # another chunking rounds differently but picks the same sign for every component
    np.testing.assert_allclose(c.weights[0], W, rtol=0, atol=1e-9)


def test_sign_convention_flips_eigh_output_consistently():
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    C = Q @ np.diag([5.0, 4.0, 3.0, 2.0, 1.0]) @ Q.T
    components, explained = pca_from_covariance(C, 3)
    np.testing.assert_allclose(explained, [5.0, 4.0, 3.0], rtol=1e-12)
    expected = Q[:, :3].T * np.sign(Q[np.argmax(np.abs(Q[:, :3]), axis=0), range(3)])[:, None]
    np.testing.assert_allclose(components, expected, atol=1e-12)


def test_constant_columns_and_full_dim_are_safe():
    X = _data(seed=4)[:200, :6]
    X[:, 2] = 7.0
    r = fit_reducer(_chunks(X, 50), method="pca", dim=6, rng=None)  # type: ignore[arg-type]
    assert r.scale[2] == 1.0 and np.all(np.isfinite(r.transform(X)))
    assert r.explained_variance[-1] == pytest.approx(0.0, abs=1e-12)
    assert r.reconstruction_error["pca"] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("method", ["pca", "ipca", "identity"])
@pytest.mark.parametrize("value", [0.1, 1e4 + 0.3, -7.0])
def test_a_constant_column_is_found_exactly_and_left_unscaled(method, value):
    # 0.1 averages to 0.10000000000000002: the column's rounding noise (sd ~ 1e-17) was
    # taken for its scale, standardising made it a unit-variance column, and PCA kept it
    # as a component in place of a real direction (reconstruction error 1/6, not 0).
    X = _data(seed=4)[:200, :6]
    X[:, 2] = value
    r = fit_reducer(_chunks(X, 7), method=method, dim=5, rng=None)  # type: ignore[arg-type]
    assert r.constant.tolist() == [False, False, True, False, False, False]
    assert r.scale[2] == 1.0 and np.all(np.isfinite(r.transform(X)))
    if method == "identity":
        np.testing.assert_allclose(r.transform(X)[:, 2], 0.0, atol=1e-9)
    else:  # the five real directions, and nothing lost
        assert r.explained_variance.min() > 1e-3
        np.testing.assert_allclose(np.abs(r.weights[0][2]), 0.0, atol=1e-9)


def test_no_rows_and_too_many_dims_are_value_errors():
    with pytest.raises(ValueError, match="no rows"):
        fit_reducer(lambda: iter([]), method="pca", dim=2, rng=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="--dim 9 exceeds the embedding's 4 columns"):
        fit_reducer(_chunks(np.eye(4), 2), method="pca", dim=9, rng=None)  # type: ignore[arg-type]


def test_reducer_files_without_explained_variance_still_load():
    """reducer.npz written before exact PCA has no explained_variance key."""
    r = fit_reducer(_chunks(_data(seed=5), 1000), method="pca", dim=3, rng=None)  # type: ignore[arg-type]
    arrays = r.to_arrays()
    np.testing.assert_array_equal(arrays["explained_variance"], r.explained_variance)
    del arrays["explained_variance"]
    old = Reducer.from_arrays(arrays)
    X = _data(seed=6)[:10]
    np.testing.assert_array_equal(old.transform(X), r.transform(X))
    assert old.explained_variance.shape == (0,)


# sklearn's IncrementalPCA divides by the total variance for its explained_variance_ratio_,
# which a pool of one point (rank 0) does not have.
@pytest.mark.filterwarnings("ignore:invalid value encountered in divide:RuntimeWarning")
@pytest.mark.parametrize("rank", [0, 1, 5, 12])
@pytest.mark.parametrize("method", ["pca", "ipca"])
@pytest.mark.parametrize("standardize", [True, False])
@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_components_beyond_the_rank_and_only_those_carry_no_variance(
    rank, method, standardize, offset
):
    # An embedding of rank r in D columns: of DIM components, the last DIM - r carry none,
    # for any offset, scaling and reducer; the direction of smallest variance the data does
    # span (1e-3 of the first, in _data) is not mistaken for none.
    rng = np.random.default_rng(rank)
    X = _data(seed=rank)[:, :rank] @ rng.normal(size=(rank, D)) if rank else np.zeros((N, D))
    X = X + offset * rng.normal(size=D)
    reducer = fit_reducer(_chunks(X, 1000), method=method, dim=DIM, standardize=standardize,
                          rng=rng)  # fmt: skip
    null = null_components(reducer.explained_variance, reducer.constant)
    assert null.tolist() == [j >= rank for j in range(DIM)]
    full = fit_reducer(_chunks(_data(), 1000), method=method, dim=D, rng=rng)
    assert not null_components(full.explained_variance).any()


def test_a_spanned_direction_far_below_the_first_is_not_called_constant():
    # Unstandardised columns of ranges 1e5 and 0.1: the second component has 1e-12 of the
    # first's variance, and its coordinate follows the second column (the GP scales it to
    # the unit cube). The 1e-10 cut called it constant; a third, unspanned one still is.
    rng = np.random.default_rng(7)
    x = np.c_[rng.uniform(0, 1e5, 5000), rng.uniform(0, 0.1, 5000)]
    X = np.c_[x, x[:, 0] - 3.0 * x[:, 1]]  # rank 2 in 3 columns
    reducer = fit_reducer(_chunks(X, 1000), method="pca", dim=3, standardize=False, rng=rng)
    lam = reducer.explained_variance
    assert 1e-13 < lam[1] / lam[0] < 1e-11
    assert null_components(lam, reducer.constant).tolist() == [False, False, True]


# ---------------------------------------------------------------------------------------
# --dim auto
# ---------------------------------------------------------------------------------------
def _factors(n: int, k: int, D: int, noise: float, seed: int) -> np.ndarray:
    """n rows of k independent factors, each of its own scale, seen through a random
    D-column linear map, plus isotropic noise."""
    rng = np.random.default_rng(seed)
    scales = np.linspace(1.0, 0.5, k)
    A = rng.normal(size=(k, D)) / np.sqrt(k)
    return (rng.normal(size=(n, k)) * scales) @ A + noise * rng.normal(size=(n, D))


@pytest.mark.parametrize("k, kept", [(3, 12), (12, 12), (18, 18), (24, 24)])
def test_auto_keeps_every_factor_of_an_embedding_and_at_least_twelve(k, kept):
    from bams_cli.core.reduce import choose_dim

    X = _factors(20_000, k, 96, 0.05, seed=k)
    red = fit_reducer(_chunks(X, 4096), dim="auto", rng=np.random.default_rng(0))
    assert red.dim == kept
    assert red.dim_choice is not None
    assert (f"after component {k}" in red.dim_choice) == (k >= 12)
    # The same numbers as the rule applied to sklearn's full spectrum of the same columns.
    S = (X - X.mean(0)) / X.std(0, ddof=1)
    assert choose_dim(PCA(svd_solver="full").fit(S).explained_variance_)[0] == kept
    # ... and the reducer is sklearn's PCA of that many components.
    ref = PCA(kept, svd_solver="full").fit(S)
    np.testing.assert_allclose(red.explained_variance, ref.explained_variance_, rtol=1e-8)


def test_auto_rule_at_its_edges():
    from bams_cli.core.reduce import AUTO_MIN_DIM, choose_dim

    assert AUTO_MIN_DIM == 12
    # A gradual decay (each eigenvalue 0.9 of the one before): no drop of 3x anywhere.
    dim, why = choose_dim(0.9 ** np.arange(64))
    assert dim == 12 and "no drop of 3x" in why
    # A cliff before 12 does not cut: small-variance directions may carry the failures.
    assert (
        choose_dim(
            [43.1, 21.5, 15.8, 8.3, 5.7, 1.5, 0.9, 0.8, 0.6, 0.6, 0.4, 0.2, 0.2, 0.1, 0.1, 0.1]
        )[0]
        == 12
    )
    # The largest drop wins, and only among components 12 to 33.
    assert choose_dim([9.0] * 14 + [3.0] * 6 + [0.5] * 20)[0] == 20
    assert choose_dim([1.0] * 40 + [1e-3] * 10)[0] == 12  # drop after 40: past the cap
    assert choose_dim([1.0] * 32 + [0.1] * 10)[0] == 32
    assert choose_dim([1.0] * 33 + [0.1] * 10)[0] == 12  # after 33: out of reach
    # A drop of less than 3x is no cliff.
    assert choose_dim([1.0] * 20 + [0.4] * 20)[0] == 12
    assert choose_dim([1.0] * 20 + [0.3] * 20) == (20, "the spectrum drops 3.3x after component 20")
    # An embedding of lower rank keeps its rank; one of 12 columns or fewer, all of them.
    assert choose_dim([3.0, 2.0, 1.0, 0.0, 0.0]) == (3, "the embedding spans 3 dimensions")
    assert choose_dim([3.0, 2.0, 1.0, 0.5]) == (4, "all 4 columns (no more than 12)")
    assert choose_dim([1.0])[0] == 1
    assert choose_dim([0.0, 0.0]) == (
        1,
        "the embedding spans no dimension: every row is the same point",
    )
    # Twelve columns are all kept; from 13 on the rule runs (a cliff after 12 or none: 12).
    assert choose_dim(0.5 ** np.arange(12)) == (12, "all 12 columns (no more than 12)")
    assert choose_dim(0.9 ** np.arange(13))[0] == 12
    assert choose_dim([1.0] * 12 + [0.1]) == (12, "the spectrum drops 10.0x after component 12")
    # Rank 5 in 20 columns: its rank, not 12 components of which 7 are empty.
    assert choose_dim([5.0, 4.0, 3.0, 2.0, 1.0] + [0.0] * 15) == (
        5,
        "the embedding spans 5 dimensions",
    )
    with pytest.raises(ValueError, match="finite spectrum"):
        choose_dim([1.0, np.nan, 0.5])
    with pytest.raises(ValueError, match="finite spectrum"):
        choose_dim([])


def test_auto_dim_is_chosen_the_same_way_by_every_method():
    X = _factors(3_000, 16, 40, 0.05, seed=1)
    rng = np.random.default_rng(0)
    pca = fit_reducer(_chunks(X, 500), dim="auto", rng=rng)
    ipca = fit_reducer(_chunks(X, 500), method="ipca", dim="auto", rng=rng)
    auto = fit_reducer(
        _chunks(X, 500), method="autoencoder", dim="auto", rng=rng, sample=X[:600], max_iter=5
    )
    assert pca.dim == ipca.dim == auto.dim == 16
    assert pca.dim_choice == ipca.dim_choice == auto.dim_choice
    assert auto.transform(X[:3]).shape == (3, 16)
    # The identity keeps the columns whatever dim says.
    assert fit_reducer(_chunks(X, 500), method="identity", dim="auto", rng=rng).dim == 40
