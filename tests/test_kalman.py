"""torchseam.core.kalman: the textbook equations, numpy and torch alike."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchseam.core import kalman


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + 0.1 * np.eye(n)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([2, 4]))
def test_update_is_the_optimal_update_and_the_backends_agree(seed, n):
    """w = 1: the Joseph form equals (I - K H) P for the optimal gain; numpy and torch give the
    same numbers; the posterior covariance is symmetric, positive and no larger than the
    prior; w = 0 leaves the state as it was."""
    rng = np.random.default_rng(seed)
    x, P, F, Q = rng.normal(size=n), _spd(rng, n), rng.normal(size=(n, n)), _spd(rng, n)
    H, R = rng.normal(size=(2, n)), _spd(rng, 2)
    z = rng.normal(size=2)
    x1, P1 = kalman.predict(x, P, F, Q)
    np.testing.assert_allclose(P1, F @ P @ F.T + Q)
    inn = kalman.innovation(x1, P1, z, H, R)
    x2, P2 = kalman.update(x1, P1, inn, H, R)
    K = P1 @ H.T @ np.linalg.inv(H @ P1 @ H.T + R)
    np.testing.assert_allclose(x2, x1 + K @ (z - H @ x1), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P2, (np.eye(n) - K @ H) @ P1, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(P2, P2.T, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(P2) > 0)
    assert np.all(np.linalg.eigvalsh(P1 - P2) > -1e-9)
    y = z - H @ x1
    np.testing.assert_allclose(float(inn.d2), y @ np.linalg.solve(inn.S, y), rtol=1e-9)
    t = {k: torch.from_numpy(v) for k, v in dict(x=x1, P=P1, z=z, H=H, R=R).items()}
    tinn = kalman.innovation(t["x"], t["P"], t["z"], t["H"], t["R"])
    tx, tP = kalman.update(t["x"], t["P"], tinn, t["H"], t["R"])
    np.testing.assert_allclose(tx.numpy(), x2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(tP.numpy(), P2, rtol=1e-9, atol=1e-12)
    x0, P0 = kalman.update(x1, P1, inn, H, R, 0.0)
    np.testing.assert_array_equal(x0, x1)
    np.testing.assert_allclose(P0, P1)


def test_a_weighted_update_has_a_gradient_in_its_weight():
    """A gate's straight-through weight: the state moves with it, differentiably."""
    x, P = torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64)
    I2 = torch.eye(2, dtype=torch.float64)
    w = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    inn = kalman.innovation(x, P, torch.tensor([2.0, 0.0], dtype=torch.float64), I2, I2)
    x1, _ = kalman.update(x, P, inn, I2, I2, w)
    x1[0].backward()
    assert x1[0].item() == 0.5 and w.grad is not None and w.grad.item() == 1.0
