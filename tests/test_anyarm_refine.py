"""darp.calibration.anyarm_refine's noise-model choice: the rotation covariance that explains residuals wins."""

from __future__ import annotations

import numpy as np

from darp.calibration.anyarm_refine import rotation_nll


def _whitening(covs: np.ndarray) -> np.ndarray:
    return np.linalg.cholesky(np.linalg.inv(covs)).transpose(0, 2, 1)


def test_rotation_nll_prefers_the_covariance_that_drew_the_residuals() -> None:
    rng = np.random.default_rng(0)
    n = 60
    axes = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]  # each capture's own tilt axes
    aniso = np.einsum("nij,j,nkj->nik", axes, np.array([9.0, 9.0, 0.25]), axes)  # tilt 6x less certain
    iso = np.repeat(np.eye(3)[None], n, 0)
    for truth, other in ((aniso, iso), (iso, aniso)):
        e = np.einsum("nij,nj->ni", np.linalg.cholesky(truth), rng.normal(size=(n, 3)))
        scores = []
        for cov in (truth, other):
            L = _whitening(cov)
            scores.append(rotation_nll(np.einsum("nij,nj->ni", L, e), L))
        assert scores[0] < scores[1] - 10.0  # clearly: a common scale cannot make up for the wrong shape


def test_rotation_nll_is_scale_free() -> None:
    """Multiplying every covariance by a constant changes nothing (the common variance is profiled out)."""
    rng = np.random.default_rng(1)
    e = rng.normal(size=(20, 3))
    covs = np.repeat(np.diag([1.0, 2.0, 3.0])[None], 20, 0)
    a, b = _whitening(covs), _whitening(25.0 * covs)
    assert abs(rotation_nll(np.einsum("nij,nj->ni", a, e), a) - rotation_nll(np.einsum("nij,nj->ni", b, e), b)) < 1e-8
