"""The behind rule pooled over a track's last frames (app/filter/behind_pool.py): the closed form, the
window, and what pooling buys against binomial counts of a right and of a slightly wrong pose."""
from __future__ import annotations

import numpy as np
import pytest

from app.filter.behind_pool import BehindPool
from app.filter.status import MAX_BEHIND_EXCESS


def test_pooled_excess_matches_the_closed_form():
    """k equal frames: (k b M − k μ − z sqrt(k v)) / (k M) = b − μ/M − z sqrt(v) / (M sqrt(k)); one frame
    is the frame's own test, b − (μ + z sqrt(v)) / M (app/filter/behind_noise.py ``behind_bound``)."""
    b, mu, v, M, z = 0.006, 2.6, 2.59, 1300, 3.0
    pool = BehindPool(30, z)
    for k in range(1, 31):
        got = pool.add(b, mu, v, M)
        assert got == pytest.approx(b - mu / M - z * np.sqrt(v) / (M * np.sqrt(k)), rel=1e-12)
    assert BehindPool(1, z).add(b, mu, v, M) == pytest.approx(b - (mu + z * np.sqrt(v)) / M, rel=1e-12)


def test_the_window_forgets_and_unknown_noise_is_not_pooled():
    pool = BehindPool(3, 3.0)
    pool.add(0.05, 2.0, 2.0, 1000)                        # a slid frame
    for _ in range(2):
        assert pool.add(0.0, 2.0, 2.0, 1000) > 0.0        # still in the pool
    assert pool.add(0.0, 2.0, 2.0, 1000) < 0.0            # three frames later it has left
    assert np.isnan(pool.add(0.01, float("nan"), float("nan"), 1000))
    pool.reset()
    assert pool.add(0.002, 2.0, 2.0, 1000) == pytest.approx(BehindPool(1, 3.0).add(0.002, 2.0, 2.0, 1000))
    with pytest.raises(ValueError, match="frames 0"):
        BehindPool(0, 3.0)


def test_pooling_finds_a_repeated_excess_that_one_frame_cannot(rng):
    """Counts drawn as the noise model says (binomial, e = 0.2 % of M = 1,300 measurements, crest_right_02's
    deep-tissue frames, BENCHMARKS.md §6i). A right pose: the pooled rule (30 frames) fires on none of
    2,000 frames at ``max_behind_excess``. A pose whose fit sits at its frame's own bound on every frame
    (3 standard deviations more behind than the noise's mean: the deep tissue's fits 1.3 mm off, whose
    share was 0.0055 against a bound of 0.0059): the frame's own test fires on a few % of the frames, the
    pooled one on nearly every frame after its first ones."""
    M, e, z = 1300, 0.002, 3.0
    mu, var = M * e, M * e * (1 - e)

    def fired(extra, frames):
        pool = BehindPool(frames, z)
        counts = rng.binomial(M, e, 2000) + extra
        return np.array([pool.add(c / M, mu, var, M) > MAX_BEHIND_EXCESS for c in counts])

    assert not fired(0, 30).any()
    at_bound = int(round(z * np.sqrt(var)))
    single, pooled = fired(at_bound, 1), fired(at_bound, 30)
    print(f"fired: one frame {single.mean():.3f}, pooled {pooled[30:].mean():.3f}")
    assert single.mean() < 0.1
    assert pooled[30:].mean() > 0.95


def test_the_track_reports_the_pooled_excess_and_forgets_it_with_a_new_track():
    """RefinedTrack (app/filter/refine_track.py) on a stub refinement whose fit sits at its frame's own
    bound on every frame: the outcome's behind evidence stays ~0 with ``behind_frames`` 1 and rises
    above ``max_behind_excess`` with 30; a new track (seed) starts the pool again."""
    from types import SimpleNamespace

    from app.filter.behind_noise import noise_bound
    from app.filter.refine import RefineResult
    from app.filter.refine_track import RefineConfig, RefinedTrack

    M, mu, var, z = 1300, 2.6, 2.59, 3.0
    at_bound = noise_bound(mu, var, M, z)
    T = np.eye(4)
    T[2, 3] = 0.42

    class Refiner:
        params = SimpleNamespace(start_width=0.010, stride=2, rerender_step=5e-4, behind_z=z)
        center = np.zeros(3)

        def refine(self, depth, T_camera_bone, start_width=None):
            return RefineResult(T.copy(), 1e8 * np.eye(6), 0.9, M, int(0.9 * M), 1200, 1e-3, True, 0.8,
                                at_bound, at_bound, 1e-3, 2, mu, var)

    def behind(frames, n):
        track = RefinedTrack(Refiner(), RefineConfig(static_prior=False, behind_frames=frames, seed_starts=0),
                             np.zeros((4, 3)), inflation=6.0)
        track.seed(T)
        return track, [track.update(np.zeros((2, 2)), np.eye(4), T).behind for _ in range(n)]

    _, single = behind(1, 40)
    assert max(single) == pytest.approx(0.0, abs=1e-12)
    track, pooled = behind(30, 40)
    assert pooled[0] == pytest.approx(0.0, abs=1e-12) and pooled[-1] > MAX_BEHIND_EXCESS
    track.seed(T)
    assert track.update(np.zeros((2, 2)), np.eye(4), T).behind == pytest.approx(0.0, abs=1e-12)
