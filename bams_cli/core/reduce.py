"""Dimensionality reduction of segment embeddings (paper section 4, "Embedding model").

Embeddings arrive as 512-d vectors; the GP works in d ~ 12 dimensions. Two reducers:

- ``pca``: optional standardisation, then ``IncrementalPCA`` fed one batch at a time, so
  memory stays flat in the pool size N (two streaming passes: statistics, then PCA).
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
from numpy.typing import NDArray
from sklearn.decomposition import PCA, IncrementalPCA
from sklearn.neural_network import MLPRegressor

Method = Literal["pca", "autoencoder", "identity"]
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
        if self.method == "pca":
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
        )


def _moments(batches: BatchSource) -> tuple[NDArray, NDArray, int]:
    """Streaming mean and standard deviation (Chan et al. parallel update), one pass."""
    n = 0
    mean = M2 = None
    for B in batches():
        B = np.asarray(B, dtype=np.float64)
        nb = B.shape[0]
        if nb == 0:
            continue
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
    # Constant columns carry no information; leave them unscaled rather than divide by 0.
    std[std == 0] = 1.0
    return mean, std, n


def fit_reducer(
    batches: BatchSource,
    *,
    method: Method = "pca",
    dim: int = 12,
    standardize: bool = True,
    sample: NDArray[np.float64] | None = None,
    rng: np.random.Generator,
    hidden: int = 128,
    max_iter: int = 200,
    progress: Progress | None = None,
) -> Reducer:
    """Fit a reducer on a stream of embedding batches.

    Parameters
    ----------
    batches : callable returning an iterable of ndarray of shape (b, D)
        Called once per pass; each call must restart the stream.
    sample : ndarray of shape (s, D), optional
        Random sample of rows: trains the autoencoder and measures reconstruction error.
    """
    mean, scale, n = _moments(batches)
    if progress:
        progress("statistics", 1, 1)
    if not standardize:
        scale = np.ones_like(scale)
    D = mean.shape[0]
    if method == "identity":
        return Reducer("identity", mean if standardize else np.zeros(D), scale)
    if dim > D:
        raise ValueError(f"--dim {dim} exceeds the embedding's {D} columns")

    ipca = IncrementalPCA(n_components=dim)
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
        ipca.partial_fit(Z)
        done += Z.shape[0]
        if progress:
            progress("pca", done, n)
    if carry is not None:
        ipca.partial_fit(carry)
    pca = Reducer("pca", mean, scale, weights=[ipca.components_.T.copy()], biases=[np.zeros(dim)])

    if sample is not None and len(sample):
        Zs = (np.asarray(sample, dtype=np.float64) - mean) / scale
        pca.reconstruction_error["pca"] = _pca_error(ipca, Zs)
    if method == "pca":
        return pca
    if sample is None or len(sample) < 2 * dim:
        raise ValueError("the autoencoder needs a training sample of at least 2 * dim rows")
    return _fit_autoencoder(Zs, mean, scale, dim, hidden, max_iter, rng, pca.reconstruction_error)


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
