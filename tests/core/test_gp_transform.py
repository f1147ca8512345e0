"""The output transform: its algebra, and the evidence that chooses it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bams_cli.core.gp import OutputTransform, fit_transformed
from bams_cli.core.gp.transform import candidate_transforms


@pytest.mark.parametrize("scale", [0.3, 2.0, 50.0])
def test_asinh_transform_algebra(scale):
    g = OutputTransform(centre=0.5, scale=scale)
    y = np.linspace(-40, 300, 101)
    np.testing.assert_allclose(g.inverse(g.forward(y)), y, rtol=1e-10, atol=1e-9)
    assert float(g.forward(0.5)) == 0.5  # the centre (the first gamma) is a fixed point
    assert np.all(np.diff(g.forward(y)) > 0)  # increasing: failure keeps its meaning
    # log Jacobian against a central difference of g
    h = 1e-6
    num = np.log((g.forward(y + h) - g.forward(y - h)) / (2 * h))
    assert g.log_jacobian(y) == pytest.approx(num.sum(), rel=1e-6)
    assert OutputTransform.from_dict(g.to_dict()) == g


def test_identity_is_the_default_and_reads_from_older_models():
    g = OutputTransform.from_dict(None)
    assert g.is_identity and g.log_jacobian([1.0, 2.0]) == 0.0
    assert g.to_dict() == {"kind": "identity"}
    np.testing.assert_array_equal(g.forward([1.0, -3.0]), [1.0, -3.0])
    with pytest.raises(ValueError, match="unknown output transform"):
        OutputTransform.from_dict({"kind": "log"})


def test_candidates_scale_with_the_spread_around_the_centre():
    cands = candidate_transforms(np.array([0.0, 10.0, 20.0, 30.0]), centre=0.0)
    assert cands[0].is_identity
    assert [c.scale for c in cands[1:]] == [15.0, 3.75]  # median |y - c| = 15
    assert len(candidate_transforms(np.zeros(3), centre=0.0)) == 1  # no spread: identity only


def _smooth(X):
    return np.sin(2 * X[:, 0]) + 0.5 * np.cos(3 * X[:, 1])


def test_evidence_chooses_the_identity_for_a_smooth_metric():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (60, 2))
    y = _smooth(X) + 0.01 * rng.normal(size=60)
    _, g, evidence = fit_transformed(
        X, np.zeros(60, int), y, 1, centre=0.0, rng=np.random.default_rng(0)
    )
    assert g.is_identity and len(evidence) == 3
    assert evidence[0]["log_evidence"] == max(e["log_evidence"] for e in evidence)


def test_evidence_chooses_a_compression_for_a_metric_with_a_wide_range():
    """y = c + s sinh(h / s) for a smooth h: near c it moves by fractions of a unit, far
    away by tens. The asinh transform at (about) s undoes the warp; the evidence finds it,
    and the model of g(y) predicts held-out failures better than the model of y."""
    rng = np.random.default_rng(1)
    X = rng.uniform(-1, 1, (80, 2))
    Xt = rng.uniform(-1, 1, (2000, 2))
    c = 0.0

    def metric(X):
        h = 3.0 * _smooth(X) + 1.0
        return c + 0.25 * np.sinh(h / 0.25 / 4)  # spans ~0.01 to ~50

    y = metric(X)
    model, g, evidence = fit_transformed(
        X, np.zeros(80, int), y, 1, centre=c, rng=np.random.default_rng(0)
    )
    assert not g.is_identity
    ident = fit_transformed(
        X, np.zeros(80, int), y, 1, centre=c, rng=np.random.default_rng(0),
        transform=OutputTransform(centre=c),
    )[0]  # fmt: skip
    fail = metric(Xt) <= c
    assert 0.05 < fail.mean() < 0.6
    p_g = model.score(Xt, g.forward([c]))[2][:, 0]
    p_id = ident.score(Xt, [c])[2][:, 0]
    brier = [np.mean((p - fail) ** 2) for p in (p_g, p_id)]
    assert brier[0] < 0.7 * brier[1], brier
    assert math.isfinite(evidence[1]["log_evidence"])


@pytest.mark.parametrize("order", ["as_given", "reversed"])
def test_the_chosen_model_is_the_chosen_candidate_s_own_fit(order, monkeypatch):
    """fit_transformed keeps one conditioned model at a time (each holds an n x n factor;
    two doubled fit's peak memory) and conditions the best again unless it came last: the
    answer is still exactly that candidate's own fit, wherever it stands in the list."""
    from bams_cli.core.gp import fit as gp_fit
    from bams_cli.core.gp import fit_mfgp

    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (70, 2))
    levels = (rng.uniform(size=70) < 0.4).astype(np.int64)
    y = _smooth(X) + 0.2 * levels + 0.01 * rng.normal(size=70)
    listed = candidate_transforms(y, 0.0)
    if order == "reversed":
        listed = listed[::-1]
        monkeypatch.setattr(gp_fit, "candidate_transforms", lambda y, c, given=listed: given)
    model, g, evidence = fit_transformed(X, levels, y, 2, centre=0.0, rng=np.random.default_rng(5))
    seed = int(np.random.default_rng(5).integers(2**63))
    fits = [fit_mfgp(X, levels, c.forward(y), 2, rng=np.random.default_rng(seed)) for c in listed]
    scores = [f.log_posterior + c.log_jacobian(y) for f, c in zip(fits, listed, strict=True)]
    assert [e["log_evidence"] for e in evidence] == scores
    k = int(np.argmax(scores))
    assert g == listed[k]
    ref = fits[k]
    assert model.hyperparameters.to_dict() == ref.hyperparameters.to_dict()
    assert model.log_posterior == ref.log_posterior
    assert (model.fitted_on, model.notes) == (ref.fitted_on, ref.notes)
    grid = rng.uniform(-1, 1, (50, 2))
    np.testing.assert_array_equal(model.predict_theta0(grid)[0], ref.predict_theta0(grid)[0])
    # the two orders put the winner at different places: one of them exercised the refit
    assert k != len(listed) - 1 or order == "reversed"
