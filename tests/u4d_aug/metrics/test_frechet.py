"""Fréchet distance and polynomial MMD: zero on identical sets, symmetric, closed forms for Gaussians."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from u4d_aug.errors import InputError
from u4d_aug.metrics import frechet
from u4d_aug.metrics.frechet import (
    feature_statistics,
    frechet_distance,
    frechet_from_features,
    polynomial_mmd,
)


def _random_spd(rng: np.random.Generator, dim: int) -> np.ndarray:
    a = rng.standard_normal((dim, dim))
    return a @ a.T / dim + 0.1 * np.eye(dim)


def test_golden_one_dimensional() -> None:
    # N(0, 1) vs N(1, 4): 1 + 1 + 4 - 2 * sqrt(1 * 4) = 2
    assert frechet_distance(np.array([0.0]), np.array([[1.0]]), np.array([1.0]), np.array([[4.0]])) == pytest.approx(
        2.0
    )


def test_identical_statistics_give_zero(rng: np.random.Generator) -> None:
    features = rng.standard_normal((200, 16))
    mu, sigma = feature_statistics(features)
    assert frechet_distance(mu, sigma, mu, sigma) == pytest.approx(0.0, abs=1e-8)
    for method in ("sqrtm", "gram", "auto"):
        assert frechet_from_features(features, features, method=method) == pytest.approx(0.0, abs=1e-8)


def test_feature_statistics_match_numpy(rng: np.random.Generator) -> None:
    features = rng.standard_normal((50, 7))
    mu, sigma = feature_statistics(features)
    np.testing.assert_allclose(mu, features.mean(0))
    np.testing.assert_allclose(sigma, np.cov(features, rowvar=False))


def test_symmetric(rng: np.random.Generator) -> None:
    mu1, mu2 = rng.standard_normal(6), rng.standard_normal(6)
    s1, s2 = _random_spd(rng, 6), _random_spd(rng, 6)
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(frechet_distance(mu2, s2, mu1, s1), rel=1e-9)
    f1, f2 = rng.standard_normal((40, 10)), rng.standard_normal((30, 10)) + 0.3
    assert frechet_from_features(f1, f2) == pytest.approx(frechet_from_features(f2, f1), rel=1e-9)


def test_diagonal_gaussians_closed_form(rng: np.random.Generator) -> None:
    # Commuting covariances: FD = ||mu1 - mu2||^2 + sum (sqrt(a) - sqrt(b))^2.
    a, b = rng.uniform(0.5, 3.0, 8), rng.uniform(0.5, 3.0, 8)
    mu1, mu2 = rng.standard_normal(8), rng.standard_normal(8)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-9)
    # Samples converge to the closed form (sampling error ~ D / sqrt(N)).
    f1 = mu1 + rng.standard_normal((20000, 8)) * np.sqrt(a)
    f2 = mu2 + rng.standard_normal((20000, 8)) * np.sqrt(b)
    assert frechet_from_features(f1, f2) == pytest.approx(expected, abs=0.05)


def test_non_commuting_covariances_match_symmetric_form(rng: np.random.Generator) -> None:
    # Tr (S1 S2)^(1/2) = Tr (S1^(1/2) S2 S1^(1/2))^(1/2), the latter from eigenvalues of a symmetric matrix.
    s1, s2 = _random_spd(rng, 12), _random_spd(rng, 12)
    mu1, mu2 = rng.standard_normal(12), rng.standard_normal(12)
    root1 = scipy.linalg.sqrtm(s1).real
    trace_covmean = np.sqrt(np.clip(np.linalg.eigvalsh(root1 @ s2 @ root1), 0, None)).sum()
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1) + np.trace(s2) - 2 * trace_covmean
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-8)


@pytest.mark.parametrize(("num1", "num2", "dim"), [(30, 25, 64), (300, 200, 20)])
def test_gram_equals_sqrtm(rng: np.random.Generator, num1: int, num2: int, dim: int) -> None:
    # Fewer samples than dimensions (rank-deficient covariances) and the ordinary case.
    f1 = rng.standard_normal((num1, dim))
    f2 = rng.standard_normal((num2, dim)) * 1.5 + 0.2
    sqrtm_value = frechet_from_features(f1, f2, method="sqrtm")
    assert frechet_from_features(f1, f2, method="gram") == pytest.approx(sqrtm_value, rel=1e-6)


def test_retry_with_eps_when_sqrtm_fails(monkeypatch: pytest.MonkeyPatch, rng: np.random.Generator) -> None:
    real_sqrtm = scipy.linalg.sqrtm
    calls = []

    def flaky_sqrtm(matrix: np.ndarray) -> np.ndarray:
        calls.append(matrix)
        return np.full_like(matrix, np.nan) if len(calls) == 1 else real_sqrtm(matrix)

    monkeypatch.setattr(frechet.scipy.linalg, "sqrtm", flaky_sqrtm)
    s = _random_spd(rng, 4)
    with pytest.warns(UserWarning, match="eps"):
        value = frechet_distance(np.zeros(4), s, np.zeros(4), s, eps=1e-6)
    assert len(calls) == 2
    assert value == pytest.approx(0.0, abs=1e-4)


def test_bad_inputs_raise_input_error(rng: np.random.Generator) -> None:
    with pytest.raises(InputError, match="feature sizes differ"):
        frechet_from_features(rng.standard_normal((5, 3)), rng.standard_normal((5, 4)))
    with pytest.raises(InputError, match="N >= 2"):
        frechet_from_features(rng.standard_normal((1, 3)), rng.standard_normal((5, 3)))
    with pytest.raises(InputError, match="method"):
        frechet_from_features(rng.standard_normal((5, 3)), rng.standard_normal((5, 3)), method="nope")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="NaN"):
        frechet_from_features(np.full((5, 3), np.nan), rng.standard_normal((5, 3)))
    with pytest.raises(InputError, match="mu"):
        frechet_distance(np.zeros(3), np.eye(3), np.zeros(2), np.eye(2))


def test_polynomial_mmd_same_distribution_near_zero_and_grows_with_shift(rng: np.random.Generator) -> None:
    f1 = rng.standard_normal((400, 32))
    f2 = rng.standard_normal((400, 32))
    same = polynomial_mmd(f1, f2, np.random.default_rng(1), num_subsets=20, max_subset_size=200)
    shifted = polynomial_mmd(f1, f2 + 0.5, np.random.default_rng(1), num_subsets=20, max_subset_size=200)
    far = polynomial_mmd(f1, f2 + 1.0, np.random.default_rng(1), num_subsets=20, max_subset_size=200)
    assert abs(same) < 0.02
    assert shifted > 10 * abs(same)
    assert far > shifted


def test_polynomial_mmd_seeded_and_golden() -> None:
    # 1-D sets {0, 1} vs {0, 1}, m = 2: k = (xy + 1)^3 gives [[1, 1], [1, 8]] within and across sets.
    # Off-diagonal within-set sum = 2 * (1 + 1) = 4, cross sum = 11: (4 / (m - 1) - 11 * 2 / m) / m = -3.5
    # (the unbiased estimate can be negative on tiny sets).
    x = np.array([[0.0], [1.0]])
    value = polynomial_mmd(x, x, np.random.default_rng(0), num_subsets=3, max_subset_size=2)
    assert value == pytest.approx(-3.5)
    f1 = np.random.default_rng(3).standard_normal((60, 5))
    f2 = np.random.default_rng(4).standard_normal((50, 5))
    first = polynomial_mmd(f1, f2, np.random.default_rng(7), num_subsets=5, max_subset_size=20)
    second = polynomial_mmd(f1, f2, np.random.default_rng(7), num_subsets=5, max_subset_size=20)
    assert first == second


def test_polynomial_mmd_cached_kernels_match_per_subset(monkeypatch: pytest.MonkeyPatch) -> None:
    f1 = np.random.default_rng(5).standard_normal((80, 6))
    f2 = np.random.default_rng(6).standard_normal((70, 6)) + 0.3
    cached = polynomial_mmd(f1, f2, np.random.default_rng(2), num_subsets=10, max_subset_size=30)
    monkeypatch.setattr(frechet, "_KERNEL_CACHE_MAX_ROWS", 0)
    per_subset = polynomial_mmd(f1, f2, np.random.default_rng(2), num_subsets=10, max_subset_size=30)
    assert cached == pytest.approx(per_subset, rel=1e-10)
