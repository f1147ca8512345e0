"""Dimensionality reduction of segment embeddings (paper section 4, "Embedding model").

Embeddings arrive as 512-d vectors; the GP works in a few dimensions, by default 12 or, where
the embedding's spectrum shows more factors than that, as many (``choose_dim``, ``--dim
auto``). Reducers:

- ``pca``: exact PCA from one streaming pass. Each batch adds its centred scatter
  ``Bc^T Bc`` (one BLAS product, float64) to a running D x D scatter matrix with Chan,
  Golub & LeVeque's pairwise update, which also yields the mean and per-column scale for
  the optional standardisation; an eigendecomposition of the D x D covariance (or
  correlation) matrix gives the components. Memory is O(D^2 + batch), flat in the pool
  size N.
- ``ipca``: the previous reducer, kept for comparison: standardisation statistics in one
  pass, then ``IncrementalPCA`` fed one batch at a time (approximate; ~7x slower).
- ``autoencoder``: the paper's encoder-decoder, an MLP 512 -> h -> d -> h -> 512 trained to
  reconstruct (standardised) embeddings on a random sample; the encoder half maps segments.
- ``identity``: keep the columns as they are (for inputs that are already low-dimensional,
  such as the 2-d synthetic problem).

A reducer is a plain set of arrays (``to_arrays`` / ``from_arrays``) so the state layer can
save it without pickling.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.decomposition import PCA, IncrementalPCA
from sklearn.neural_network import MLPRegressor

Method = Literal["pca", "ipca", "autoencoder", "identity"]
#: A reduced dimension, or "auto": chosen from the embedding's spectrum (``choose_dim``).
Dim = int | Literal["auto"]
AUTO: Literal["auto"] = "auto"
BatchSource = Callable[[], Iterable[NDArray[np.float64]]]
Progress = Callable[[str, int, int], None]


@dataclass
class Reducer:
    """A fitted map from raw embeddings (D columns) to reduced coordinates (d columns)."""

    method: str
    mean: NDArray[np.float64]  # (D,)
    scale: NDArray[np.float64]  # (D,)
    weights: list[NDArray[np.float64]] = field(default_factory=list)
    biases: list[NDArray[np.float64]] = field(default_factory=list)
    reconstruction_error: dict[str, float] = field(default_factory=dict)
    # PCA only: variance along each component (ddof = 1, standardised units if standardised).
    explained_variance: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    # (D,) after a fit, empty once loaded: input columns with one value in every row. Not
    # saved; embed-reduce warns about them.
    constant: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    # After a fit with dim "auto": why this many components (``choose_dim``). Not saved;
    # the pool's metadata keeps it.
    dim_choice: str | None = None

    @property
    def dim(self) -> int:
        if self.method == "identity":
            return int(self.mean.shape[0])
        return int(self.weights[-1].shape[1])

    def transform(self, E: NDArray[np.float64]) -> NDArray[np.float64]:
        """Map raw embeddings.

        Parameters
        ----------
        E : ndarray of shape (n, D)

        Returns
        -------
        Z : ndarray of shape (n, d)
        """
        Z = (np.asarray(E, dtype=np.float64) - self.mean) / self.scale
        if self.method == "identity":
            return Z
        if self.method in ("pca", "ipca"):
            return Z @ self.weights[0]
        # Encoder half of the autoencoder: tanh hidden layers, bottleneck activations.
        for W, b in zip(self.weights, self.biases, strict=True):
            Z = np.tanh(Z @ W + b)
        return Z

    def to_arrays(self) -> dict[str, NDArray]:
        out: dict[str, NDArray] = {
            "method": np.array(self.method),
            "mean": self.mean,
            "scale": self.scale,
            "n_layers": np.array(len(self.weights)),
        }
        for i, (W, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            out[f"W{i}"], out[f"b{i}"] = W, b
        for key, value in self.reconstruction_error.items():
            out[f"err_{key}"] = np.array(value)
        if len(self.explained_variance):
            # An extra key only: files without it (written before exact PCA) still load,
            # and older readers ignore it.
            out["explained_variance"] = self.explained_variance
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, NDArray]) -> Reducer:
        n = int(arrays["n_layers"])
        return cls(
            method=str(arrays["method"]),
            mean=np.asarray(arrays["mean"], dtype=np.float64),
            scale=np.asarray(arrays["scale"], dtype=np.float64),
            weights=[np.asarray(arrays[f"W{i}"]) for i in range(n)],
            biases=[np.asarray(arrays[f"b{i}"]) for i in range(n)],
            reconstruction_error={
                k[4:]: float(v) for k, v in arrays.items() if k.startswith("err_")
            },
            explained_variance=np.asarray(
                arrays.get("explained_variance", np.zeros(0)), dtype=np.float64
            ),
        )


def _moments(batches: BatchSource) -> tuple[NDArray, NDArray, int, NDArray[np.bool_]]:
    """Streaming mean and standard deviation (Chan et al. parallel update), one pass; and
    which columns are constant (``_Span.constant``)."""
    n = 0
    mean = M2 = None
    span = _Span()
    for B in batches():
        B = np.asarray(B, dtype=np.float64)
        nb = B.shape[0]
        if nb == 0:
            continue
        span.update(B)
        mb = B.mean(axis=0)
        M2b = ((B - mb) ** 2).sum(axis=0)
        if mean is None:
            mean, M2, n = mb, M2b, nb
            continue
        delta = mb - mean
        total = n + nb
        mean = mean + delta * nb / total
        M2 = M2 + M2b + delta**2 * n * nb / total
        n = total
    if mean is None or M2 is None:
        raise ValueError("no rows to fit the reducer on")
    std = np.sqrt(M2 / max(n - 1, 1))
    constant = span.constant()
    # Constant columns carry no information; leave them unscaled rather than divide by 0
    # or by their rounding noise.
    std[constant | (std == 0)] = 1.0
    return mean, std, n, constant


class _Span:
    """Running column minima and maxima of a stream of row batches."""

    def __init__(self) -> None:
        self.lo: NDArray[np.float64] | None = None
        self.hi: NDArray[np.float64] | None = None

    def update(self, B: NDArray[np.float64]) -> None:
        lo, hi = B.min(axis=0), B.max(axis=0)
        if self.lo is None or self.hi is None:
            self.lo, self.hi = lo, hi
            return
        np.minimum(self.lo, lo, out=self.lo)
        np.maximum(self.hi, hi, out=self.hi)

    def constant(self) -> NDArray[np.bool_]:
        """Columns holding one value in every row (min == max), shape (D,).

        Exact, where the variance is not: a column of 0.1s averages to 0.10000000000000002
        and leaves a standard deviation of 7e-17, which standardising divided by and blew
        up to a unit-variance column (PCA then kept it as a component in place of a real
        direction)."""
        if self.lo is None or self.hi is None:
            raise ValueError("no rows to fit the reducer on")
        return self.lo == self.hi


class Scatter:
    """Running mean and scatter matrix of a stream of row batches (and the columns' span,
    which says exactly which are constant).

    After rows ``x_1 .. x_n``: ``mean = sum x_i / n`` and
    ``M2 = sum (x_i - mean)(x_i - mean)^T``, so the sample covariance is ``M2 / (n - 1)``.

    Each batch ``B`` is centred on its own mean before its scatter ``Bc^T Bc`` is formed
    (one BLAS product), and batches are merged with the pairwise update of Chan, Golub &
    LeVeque (1979, eq. 2.1):

        delta = mean_B - mean_A
        M2_AB = M2_A + M2_B + delta delta^T n_A n_B / (n_A + n_B)

    The naive form ``(sum x x^T - n mean mean^T) / (n - 1)`` subtracts two numbers of size
    ``n (offset^2 + var)`` to get one of size ``n var``: with a common offset of 1e4 and
    unit variance it loses eight of float64's sixteen digits. Centring each batch first
    keeps every term of size ``var``; the correction term involves only differences of
    batch means, which are small whatever the offset.
    """

    def __init__(self) -> None:
        self.n = 0
        self.mean: NDArray[np.float64] | None = None  # (D,)
        self.M2: NDArray[np.float64] | None = None  # (D, D)
        self.span = _Span()

    def update(self, B: NDArray) -> None:
        """Add a batch.

        Parameters
        ----------
        B : ndarray of shape (b, D)
        """
        B = np.asarray(B, dtype=np.float64)
        nb = B.shape[0]
        if nb == 0:
            return
        self.span.update(B)
        mb = B.mean(axis=0)
        Bc = B - mb
        # numpy computes Bc.T @ Bc with one symmetric rank-k update (BLAS syrk): half a gemm.
        M2b = Bc.T @ Bc
        if self.mean is None or self.M2 is None:
            self.n, self.mean, self.M2 = nb, mb, M2b
            return
        na, total = self.n, self.n + nb
        delta = mb - self.mean
        self.mean = self.mean + delta * (nb / total)
        M2b += np.outer(delta, delta * (na * nb / total))
        self.M2 += M2b
        self.n = total

    def covariance(self) -> NDArray[np.float64]:
        """Sample covariance (ddof = 1, as sklearn's ``PCA``), shape (D, D)."""
        if self.M2 is None:
            raise ValueError("no rows to fit the reducer on")
        return self.M2 / max(self.n - 1, 1)


def pca_from_covariance(
    C: NDArray[np.float64], dim: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Leading eigenpairs of a covariance matrix, with a deterministic sign.

    Parameters
    ----------
    C : ndarray of shape (D, D)
        Symmetric positive semi-definite.
    dim : int
        Number of components kept, ``1 <= dim <= D``.

    Returns
    -------
    components : ndarray of shape (dim, D)
        Orthonormal rows, by decreasing variance; each row's largest-magnitude loading is
        positive (the first such loading on a tie), so re-runs and other BLAS builds give the
        same coordinates rather than a sign-flipped copy.
    explained_variance : ndarray of shape (dim,)
        Eigenvalues ``lambda_1 >= ... >= lambda_dim``, rounding negatives clipped to 0.
    """
    D = C.shape[0]
    # LAPACK syevd on the symmetric matrix: eigenvalues ascending, vectors in the columns.
    lam, V = np.linalg.eigh(C)
    lam, V = lam[::-1][:dim], V[:, ::-1][:, :dim]
    components = V.T.copy()
    lead = np.argmax(np.abs(components), axis=1)
    components *= np.sign(components[np.arange(dim), lead])[:, None]
    assert components.shape == (dim, D)
    return components, np.clip(lam, 0.0, None)


#: A principal component whose variance is at most this share of the first's carries none:
#: the data does not span its direction. Rounding leaves ~1e-16 of the first's variance
#: along such directions (float64 or float32 embeddings of 16 to 512 columns, exact and
#: incremental PCA alike), a thousandth of this. A direction the data does span can be far
#: below the first under --no-standardize with mixed units (a column of range 0.1 beside
#: one of range 1e5: 1e-12), and the GP scales each reduced coordinate to the unit cube,
#: so it still informs the model: 1e-10 called that one constant.
NULL_VARIANCE_RTOL = 1e-13


def null_components(
    explained_variance: NDArray[np.float64], constant: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """Which principal components carry no variance: more components asked for than the
    embedding's rank, whose reduced coordinates are then constant.

    Parameters
    ----------
    explained_variance : ndarray of shape (d,)
        Variance along each component, decreasing (``Reducer.explained_variance``).
    constant : ndarray of bool, shape (D,), optional
        The input columns holding one value in every row (``Reducer.constant``).

    Returns
    -------
    ndarray of bool, shape (d,)
        True where the variance is at most ``NULL_VARIANCE_RTOL`` times the largest; every
        component when every input column is constant (all rows one point: what variance
        there is, is the rounding of the columns' means) or the largest is 0.
    """
    lam = np.asarray(explained_variance, dtype=np.float64)
    if constant is not None and len(constant) and np.all(constant):
        return np.ones(lam.shape, dtype=bool)
    if lam.size == 0:
        return np.zeros(0, dtype=bool)
    return lam <= NULL_VARIANCE_RTOL * lam.max()


#: ``choose_dim``: never fewer components than this (the default before ``auto``, the
#: paper's d), nor more than ``AUTO_MAX_DIM``.
AUTO_MIN_DIM = 12
AUTO_MAX_DIM = 32
#: ``choose_dim``: a drop in the spectrum by at least this factor separates the embedding's
#: factors from its noise floor.
AUTO_GAP = 3.0


def choose_dim(eigenvalues: ArrayLike) -> tuple[int, str]:
    """The reduced dimension ``--dim auto`` keeps, and why, from the PCA spectrum.

    ``AUTO_MIN_DIM`` (12) components, or more where the spectrum shows more factors than
    that: an embedding of many underlying factors seen through more columns has a spectrum
    that falls off a cliff where the factors end and the noise floor begins (a 24-factor
    latent in 96 columns: 0.80% of the variance on component 24, 0.21% on 25), and
    ``auto`` keeps the components before the largest drop lam_k / lam_(k+1) of at least
    ``AUTO_GAP`` among k = 12 .. ``AUTO_MAX_DIM``. Twelve components kept 72% of that
    embedding's variance and half its factors, and BAMS found 0.39 of the failures it
    finds with 24 (0.007 against 0.018; docs/suite/dimension.md).

    Never fewer than 12, though a cliff may come earlier: how much of the embedding's
    variance a direction carries says nothing of its bearing on failures. A 16-column
    simulator embedding whose spectrum drops 3.8x after component 5 lost a factor the
    failures hang on at 5 components (BAMS's recall 0.28 at 12 components, 0.21 at 8, 0.04
    at 5). Only an embedding of lower rank keeps fewer: its rank (the components past it
    carry no variance).

    Parameters
    ----------
    eigenvalues : array_like of shape (D,)
        Every eigenvalue of the (standardised) covariance, decreasing.

    Returns
    -------
    dim : int
        Between 1 and D.
    reason : str
        One line for the user, e.g. "the spectrum drops 11.3x after component 12".
    """
    lam = np.asarray(eigenvalues, dtype=np.float64)
    if lam.size == 0 or not np.all(np.isfinite(lam)):
        raise ValueError(f"choose_dim needs a finite spectrum, got {lam.size} eigenvalues")
    lam = np.clip(lam, 0.0, None)
    D = lam.size
    rank = int(np.sum(~null_components(lam))) if lam[0] > 0.0 else 0
    if rank == 0:
        return 1, "the embedding spans no dimension: every row is the same point"
    if rank < min(D, AUTO_MIN_DIM):
        return rank, f"the embedding spans {rank} dimension{'s' * (rank != 1)}"
    if D <= AUTO_MIN_DIM:
        return D, f"all {D} column{'s' * (D != 1)} (no more than {AUTO_MIN_DIM})"
    k = np.arange(AUTO_MIN_DIM, min(D - 1, AUTO_MAX_DIM) + 1)
    if k.size:
        with np.errstate(divide="ignore", invalid="ignore"):
            drop = np.where(lam[k] > 0.0, lam[k - 1] / lam[k], np.inf)
        best = int(np.argmax(drop))
        if drop[best] >= AUTO_GAP:
            factor = "to zero" if np.isinf(drop[best]) else f"{drop[best]:.1f}x"
            return int(k[best]), f"the spectrum drops {factor} after component {k[best]}"
    return AUTO_MIN_DIM, (
        f"{AUTO_MIN_DIM}, the least auto keeps: no drop of {AUTO_GAP:g}x in the spectrum "
        f"among components {AUTO_MIN_DIM} to {min(D, AUTO_MAX_DIM + 1)}"
    )


def fit_reducer(
    batches: BatchSource,
    *,
    method: Method = "pca",
    dim: Dim = AUTO,
    standardize: bool = True,
    sample: NDArray[np.float64] | None = None,
    rng: np.random.Generator,
    hidden: int = 128,
    max_iter: int = 200,
    progress: Progress | None = None,
    n_rows: int | None = None,
) -> Reducer:
    """Fit a reducer on a stream of embedding batches.

    Parameters
    ----------
    batches : callable returning an iterable of ndarray of shape (b, D)
        Called once per pass; each call must restart the stream. ``pca`` reads it once,
        ``ipca`` twice (three times with ``dim`` "auto": the exact spectrum first).
    sample : ndarray of shape (s, D), optional
        Random sample of rows: trains the autoencoder and measures its error (and
        ``ipca``'s). ``pca`` does not need it: its error comes from the eigenvalues.
    n_rows : int, optional
        Rows in the stream, for progress reports only.
    """
    if method in ("pca", "autoencoder"):
        pca = _fit_exact_pca(batches, dim, standardize, progress, n_rows)
        if method == "pca":
            return pca
        dim = pca.dim
        if sample is None or len(sample) < 2 * dim:
            raise ValueError("the autoencoder needs a training sample of at least 2 * dim rows")
        Zs = (np.asarray(sample, dtype=np.float64) - pca.mean) / pca.scale
        auto = _fit_autoencoder(
            Zs, pca.mean, pca.scale, dim, hidden, max_iter, rng, pca.reconstruction_error
        )
        auto.constant, auto.dim_choice = pca.constant, pca.dim_choice
        return auto

    mean, scale, n, constant = _moments(batches)
    if progress:
        progress("statistics", n, n)
    if not standardize:
        scale = np.ones_like(scale)
    D = mean.shape[0]
    if method == "identity":
        return Reducer("identity", mean if standardize else np.zeros(D), scale, constant=constant)
    dim_choice = None
    if dim == AUTO:  # one more pass: the exact spectrum decides
        exact = _fit_exact_pca(batches, AUTO, standardize, progress, n_rows)
        dim, dim_choice = exact.dim, exact.dim_choice
    if dim > D:
        raise ValueError(f"--dim {dim} exceeds the embedding's {D} columns")

    ipca = IncrementalPCA(n_components=dim)

    def fit_part(Z: NDArray) -> None:
        try:
            ipca.partial_fit(Z)
        except np.linalg.LinAlgError as exc:  # e.g. an embedding of rank below --dim
            raise ValueError(
                f"--method ipca: scikit-learn's IncrementalPCA failed ({exc}); the exact "
                "--method pca (the default) reduces any embedding, one of rank below --dim too"
            ) from None

    done = 0
    carry: NDArray | None = None
    for B in batches():
        Z = (np.asarray(B, dtype=np.float64) - mean) / scale
        # IncrementalPCA needs every partial batch to hold at least `dim` rows.
        if carry is not None:
            Z = np.vstack([carry, Z])
            carry = None
        if Z.shape[0] < dim:
            carry = Z
            continue
        fit_part(Z)
        done += Z.shape[0]
        if progress:
            progress("pca", done, n)
    if carry is not None:
        fit_part(carry)
    reducer = Reducer(
        "ipca",
        mean,
        scale,
        weights=[ipca.components_.T.copy()],
        biases=[np.zeros(dim)],
        explained_variance=np.asarray(ipca.explained_variance_, dtype=np.float64),
        constant=constant,
        dim_choice=dim_choice,
    )
    if sample is not None and len(sample):
        Zs = (np.asarray(sample, dtype=np.float64) - mean) / scale
        reducer.reconstruction_error["pca"] = _pca_error(ipca, Zs)
    return reducer


def _fit_exact_pca(
    batches: BatchSource,
    dim: Dim,
    standardize: bool,
    progress: Progress | None,
    n_rows: int | None,
) -> Reducer:
    """Exact PCA (optionally of standardised columns) in one pass over the stream."""
    acc = Scatter()
    for B in batches():
        acc.update(B)
        if progress:
            progress("pca", acc.n, max(n_rows or acc.n, acc.n))
    C = acc.covariance()
    assert acc.mean is not None
    D = C.shape[0]
    if dim != AUTO and dim > D:
        raise ValueError(f"--dim {dim} exceeds the embedding's {D} columns")
    std = np.sqrt(np.diag(C))
    constant = acc.span.constant()
    # Constant columns carry no information; leave them unscaled rather than divide by 0
    # or by their rounding noise.
    std[constant | (std == 0)] = 1.0
    scale = std if standardize else np.ones(D)
    # Covariance of the standardised columns S = (X - mean) / scale: C_ij / (s_i s_j).
    C = C / np.outer(scale, scale)
    dim_choice = None
    if dim == AUTO:
        dim, dim_choice = choose_dim(np.linalg.eigvalsh(C)[::-1])
    components, lam = pca_from_covariance(C, dim)
    # Mean squared reconstruction error per coordinate over the whole pool (ddof = 0):
    # the variance left in the discarded directions, trace(C) - sum of kept eigenvalues.
    # Clipped at 0: when dim = D (or the rank is lower) the difference is pure rounding.
    left = max(float(np.trace(C) - lam.sum()), 0.0)
    error = left * (acc.n - 1) / acc.n / D if acc.n > 1 else 0.0
    return Reducer(
        "pca",
        acc.mean,
        scale,
        weights=[components.T.copy()],
        biases=[np.zeros(dim)],
        reconstruction_error={"pca": error},
        explained_variance=lam,
        constant=constant,
        dim_choice=dim_choice,
    )


def _pca_error(pca: IncrementalPCA | PCA, Z: NDArray) -> float:
    """Mean squared reconstruction error per coordinate, in standardised units."""
    recon = pca.inverse_transform(pca.transform(Z))
    return float(np.mean((Z - recon) ** 2))


def _fit_autoencoder(
    Zs: NDArray,
    mean: NDArray,
    scale: NDArray,
    dim: int,
    hidden: int,
    max_iter: int,
    rng: np.random.Generator,
    errors: dict[str, float],
) -> Reducer:
    # sklearn's MLPRegressor trained as x -> x with a d-unit bottleneck is the paper's
    # encoder-decoder; its first two weight layers are the encoder. A fifth of the sample
    # is held out so both reducers' errors are measured on rows neither was tuned on.
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    order = rng.permutation(len(Zs))
    cut = max(1, len(Zs) // 5)
    test, train = Zs[order[:cut]], Zs[order[cut:]]
    net = MLPRegressor(
        hidden_layer_sizes=(hidden, dim, hidden),
        activation="tanh",
        max_iter=max_iter,
        early_stopping=True,
        random_state=int(rng.integers(2**31 - 1)),
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        net.fit(train, train)
    pca = PCA(n_components=dim).fit(train)
    errors = dict(errors)
    errors["pca_heldout"] = _pca_error(pca, test)
    errors["autoencoder_heldout"] = float(np.mean((test - net.predict(test)) ** 2))
    errors["autoencoder_converged"] = float(
        not any(w.category is ConvergenceWarning for w in caught)
    )
    return Reducer(
        "autoencoder",
        mean,
        scale,
        weights=[np.asarray(w) for w in net.coefs_[:2]],
        biases=[np.asarray(b) for b in net.intercepts_[:2]],
        reconstruction_error=errors,
    )
