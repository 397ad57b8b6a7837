"""Rotation helpers of torchseam.core.transforms: slerp."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from torchseam.core.transforms import matrix_to_quat, quat_to_matrix, slerp


def test_slerp_matches_scipy_takes_the_short_way_and_keeps_its_ends():
    rng = np.random.default_rng(4)
    for _ in range(50):
        R = Rotation.random(2, random_state=rng)
        q0, q1 = matrix_to_quat(R.as_matrix())
        ref = Slerp([0.0, 1.0], R)
        for u in (0.0, 0.3, 0.5, 1.0):
            got = quat_to_matrix(slerp(q0, q1, u))
            np.testing.assert_allclose(got, ref([u]).as_matrix()[0], atol=1e-9)
            # -q1 is the same rotation: the same answer
            np.testing.assert_allclose(quat_to_matrix(slerp(q0, -q1, u)), got, atol=1e-9)
        assert abs(np.linalg.norm(slerp(q0, q1, 0.7)) - 1.0) < 1e-12
    # nearly equal quaternions: no 0/0, a unit quaternion between them
    q0 = matrix_to_quat(Rotation.from_rotvec([0.0, 0.0, 1e-9]).as_matrix())
    q = slerp(np.array([1.0, 0.0, 0.0, 0.0]), q0, 0.5)
    assert np.isfinite(q).all() and abs(np.linalg.norm(q) - 1.0) < 1e-12
