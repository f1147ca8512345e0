"""Self-checks of a fitted GP: closed-form leave-one-out against brute force, paired
differences, and the warnings they give."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bams_cli.core.gp import MFGP, Hyperparameters, fit_mfgp
from bams_cli.core.gp.checks import check_model, loo_level0, paired_differences


def _hp(d=2, noise=(0.05, 0.05), s1=0.3):
    return Hyperparameters(
        mean=0.2,
        outputscale0=1.0,
        lengthscales0=np.full(d, 0.8),
        outputscales=np.array([s1]),
        lengthscales=np.full((1, d), 1.2),
        noise=np.array(noise),
        offsets=np.array([0.4]),
    )


def test_closed_form_loo_equals_refitting_without_each_point():
    """R&W eq. 5.12 against brute force: drop observation i, condition on the rest with
    the same hyperparameters, and standardise y_i by the predictive mean and variance of
    a level-0 observation (theta0 plus level-0 noise)."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(14, 2))
    levels = np.r_[np.zeros(6, int), np.ones(8, int)]
    y = np.sin(X).sum(1) + 0.4 * levels + 0.1 * rng.normal(size=14)
    hp = _hp()
    z = loo_level0(MFGP(X, levels, y, 2, hp))
    ref = []
    for i in range(6):
        keep = np.arange(14) != i
        m = MFGP(X[keep], levels[keep], y[keep], 2, hp)
        mu, s2 = m.predict_theta0(X[i : i + 1])
        ref.append((y[i] - mu[0]) / np.sqrt(s2[0] + hp.noise[0]))
    np.testing.assert_allclose(z, ref, rtol=1e-8)


def test_paired_differences_average_repeats_and_match_segments():
    seg = np.array([3, 3, 7, 3, 7, 9, 1])
    lv = np.array([0, 0, 0, 1, 1, 1, 0])
    y = np.array([1.0, 3.0, 5.0, 4.0, 4.5, 0.0, 2.0])
    np.testing.assert_allclose(paired_differences(seg, lv, y, 1), [4.0 - 2.0, 4.5 - 5.0])


def _paired_data(rng, n_pairs, disc_sd, n_cheap=40):
    X = rng.normal(size=(n_pairs + n_cheap, 2))
    f = np.sin(X[:, 0]) + 0.5 * X[:, 1]
    seg = np.r_[np.arange(n_pairs), np.arange(n_pairs + n_cheap)]
    Xo = X[seg]
    levels = np.r_[np.zeros(n_pairs, int), np.ones(n_pairs + n_cheap, int)]
    y = f[seg] + disc_sd * rng.normal(size=seg.size) * levels
    return Xo, levels, y, seg


def test_pair_check_flags_a_model_that_trusts_the_cheap_level_too_much():
    rng = np.random.default_rng(1)
    Xo, levels, y, seg = _paired_data(rng, 20, disc_sd=0.5)
    # Hyperparameters that claim the cheap level is nearly exact (sd ~0.03).
    hp = Hyperparameters(
        mean=0.0, outputscale0=1.0, lengthscales0=np.ones(2), outputscales=np.array([1e-4]),
        lengthscales=np.ones((1, 2)), noise=np.array([1e-4, 1e-4]),
    )  # fmt: skip
    checks = check_model(MFGP(Xo, levels, y, 2, hp), seg)
    pair = checks.pairs[0]
    assert pair.n_pairs == 20 and pair.sd_observed == pytest.approx(0.5, rel=0.35)
    assert pair.p_value < 1e-6
    assert any(
        "level 1 differs from level 0 more than the model allows" in w for w in checks.warnings
    )


def test_fitted_model_learns_the_discrepancy_from_pairs_and_passes_its_checks():
    rng = np.random.default_rng(2)
    Xo, levels, y, seg = _paired_data(rng, 15, disc_sd=0.4)
    model = fit_mfgp(Xo, levels, y, 2, rng=np.random.default_rng(0))
    checks = check_model(model, seg)
    fitted = np.sqrt(model.hyperparameters.outputscales[0] + model.hyperparameters.noise.sum())
    assert 0.2 < fitted < 0.8  # true sd(y1 - y0) = 0.4
    assert checks.pairs[0].p_value > 0.01
    assert not checks.warnings


def test_loo_check_flags_an_overconfident_level0_model():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(30, 2))
    y = np.sin(3 * X[:, 0]) + 0.3 * rng.normal(size=30)  # rough and noisy
    hp = Hyperparameters(
        mean=0.0, outputscale0=0.05, lengthscales0=np.full(2, 3.0), outputscales=np.zeros(0),
        lengthscales=np.zeros((0, 2)), noise=np.array([1e-4]),
    )  # fmt: skip
    checks = check_model(MFGP(X, np.zeros(30, int), y, 1, hp), np.arange(30))
    assert checks.loo_mean_z2 > 5 and checks.loo_p_value < 1e-6
    assert any("overconfident at level 0" in w for w in checks.warnings)
    doc = checks.to_dict()
    assert doc["loo_level0"]["n"] == 30 and doc["pairs"] == []


def _drawn_from_the_model(n: int):
    """n level-0 points in 2-d and values drawn from the GP itself (noise variance 0.05)."""
    from tests.core.test_gp import ref_matern52

    rng = np.random.default_rng(4)
    X = rng.uniform(-2, 2, size=(n, 2))
    hp = Hyperparameters(
        mean=0.0, outputscale0=1.0, lengthscales0=np.full(2, 0.7), outputscales=np.zeros(0),
        lengthscales=np.zeros((0, 2)), noise=np.array([0.05]),
    )  # fmt: skip
    K = ref_matern52(X, X, hp.lengthscales0, 1.0) + 0.05 * np.eye(n)
    return X, hp, np.linalg.cholesky(K) @ rng.normal(size=n)


def test_calibrated_model_has_loo_mean_square_near_one():
    """Data drawn from the model itself: the standardised LOO residuals are N(0, 1)."""
    X, hp, y = _drawn_from_the_model(150)
    checks = check_model(MFGP(X, np.zeros(150, int), y, 1, hp), np.arange(150))
    assert 0.7 < checks.loo_mean_z2 < 1.35
    assert not checks.warnings


def test_one_level0_run_far_from_its_prediction_is_flagged_by_name():
    """A mean square of z that passes can hide one run many sds off (|z| 5.5 among twenty
    in a trial study): the largest |z| gets its own Bonferroni test, and the warning names
    the segment. Data drawn from the model itself, then one result moved by 1.3 (~5 sd
    of its leave-one-out prediction)."""
    X, hp, y = _drawn_from_the_model(300)
    seg = np.arange(300) + 1000  # pool rows
    names = np.array([f"s{i:05d}" for i in range(1200)])
    calm = check_model(MFGP(X, np.zeros(300, int), y, 1, hp), seg, names=names)
    assert calm.loo_max_p_value > 0.01 and not calm.warnings
    y[37] += 1.3
    checks = check_model(MFGP(X, np.zeros(300, int), y, 1, hp), seg, names=names)
    assert checks.loo_p_value >= 0.01  # the mean square alone would not say it
    assert checks.loo_max_abs_z > 5 and checks.loo_max_row == 1037
    bound = 300 * math.erfc(checks.loo_max_abs_z / math.sqrt(2))
    assert checks.loo_max_p_value == pytest.approx(bound) and bound < 1e-4
    [w] = checks.warnings
    assert "near segment s01037" in w and f"{checks.loo_max_abs_z:.1f} sd" in w
    assert checks.to_dict()["loo_level0"]["max_p_value"] == pytest.approx(bound)


def test_above_its_cap_the_loo_check_says_it_took_a_sample(capsys):
    """The line "leave-one-out at 500 level-0 runs" of a model holding 1,022 read as a miscount: the
    check takes a random 500 (``_MAX_LOO``) and says so."""
    from bams_cli import console
    from bams_cli.core.gp.checks import _MAX_LOO

    X, hp, y = _drawn_from_the_model(_MAX_LOO + 40)
    n = y.size
    checks = check_model(MFGP(X, np.zeros(n, int), y, 1, hp), np.arange(n))
    assert (checks.loo_n, checks.to_dict()["loo_level0"]["of"]) == (_MAX_LOO, n)
    console.model_checks(checks.to_dict())
    assert f"check: leave-one-out at {_MAX_LOO} of the {n:,} level-0 runs (a random sample)" in (
        " ".join(capsys.readouterr().out.split())
    )
    small = check_model(MFGP(X[:50], np.zeros(50, int), y[:50], 1, hp), np.arange(50))
    assert small.to_dict()["loo_level0"]["of"] == 50
