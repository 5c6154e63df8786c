"""app/bench/ambiguity.py (osteonav diagnose-likelihood): the wide search's poses and the table."""
from __future__ import annotations

import numpy as np

from app.bench import ambiguity
from app.geometry import se3


def test_random_poses_stay_within_the_search_ranges(rng):
    T = se3.from_rotvec_trans(np.array([0.4, 0.1, -0.3]), np.array([0.1, 0.2, 0.5]))
    poses = ambiguity.random_poses(T, 500, 0.04, np.radians(40), rng)
    angle = se3.rotation_angle(poses, T[None])
    assert np.all(angle <= np.radians(40) + 1e-9) and angle.max() > np.radians(35)
    # the translation is drawn in the bone frame about the bone's origin: |R^T (p - p0)| <= 4 cm
    offsets = np.einsum("ji,nj->ni", T[:3, :3], poses[:, :3, 3] - T[:3, 3])
    assert np.all(np.linalg.norm(offsets, axis=1) <= 0.04 + 1e-12)
    assert all(se3.is_rigid(P) for P in poses[:20])


def test_score_batches_through_a_backend_with_a_capacity():
    class Backend:
        def log_likelihood(self, T, depth):
            assert len(T) <= 7
            return T[:, 0, 3] * 10

    poses = np.tile(np.eye(4), (20, 1, 1))
    poses[:, 0, 3] = np.arange(20)
    np.testing.assert_allclose(ambiguity.score(Backend(), poses, np.zeros((4, 4)), 7), np.arange(20) * 10)


def test_table_has_one_row_per_frame():
    row = ambiguity.FrameDiagnosis(3, 220.1, 0.84, 0.48, 198.0, 6.0, 6.3, 0.83, 0.51, 2.0, 6.5)
    text = ambiguity.table([row, row])
    assert text.count("\n| 3 |") == 2 and "220.1" in text and "2.0 / 6.5" in text
