"""The live session's joint history (app/session/bus.py JointBuffer): appended in place, the last ``seconds``
kept, interpolated at a frame's stamp; the same answers as the whole-history copy it replaced."""
from __future__ import annotations

import numpy as np

from app.geometry.ur import interpolate_joints
from app.session.bus import JointBuffer


def _reference_at(t_all, q_all, t, seconds, max_gap_s):
    """The previous implementation's answer: keep t >= t[-1] - seconds of everything added, interpolate."""
    keep = t_all >= t_all[-1] - seconds
    stamps, q = t_all[keep], q_all[keep]
    if t > stamps[-1] or t < stamps[0]:
        return None
    hi = int(np.searchsorted(stamps, t, side="left"))
    lo = max(hi - 1, 0)
    if stamps[hi] - stamps[lo] > max_gap_s:
        return None
    qi, valid = interpolate_joints(stamps[lo:hi + 1], q[lo:hi + 1], np.array([t]))
    return qi[0] if valid[0] else None


def test_the_buffer_answers_as_the_whole_history_over_many_batches_and_moves():
    rng = np.random.default_rng(3)
    buf = JointBuffer(seconds=0.5, max_gap_s=0.05)
    t_all, q_all = np.empty(0), np.empty((0, 6))
    t = 100.0
    for batch in range(400):                            # many moves of the 1,024-row start
        n = int(rng.integers(0, 12))
        stamps = t + np.cumsum(rng.uniform(0.001, 0.004, n)) + (0.08 if batch % 97 == 5 else 0.0)   # and a gap
        t = stamps[-1] if n else t
        q = rng.normal(size=(n, 6))
        buf.add(stamps, q)
        t_all, q_all = np.concatenate([t_all, stamps]), np.concatenate([q_all, q])
        if not len(t_all):
            continue
        np.testing.assert_array_equal(buf._t, t_all[t_all >= t_all[-1] - 0.5])
        for query in rng.uniform(t_all[-1] - 0.7, t_all[-1] + 0.01, 5):
            got, why = buf.at(float(query))
            want = _reference_at(t_all, q_all, float(query), 0.5, 0.05)
            assert (got is None) == (want is None), (query, why)
            if want is not None:
                np.testing.assert_array_equal(got, want)
    assert buf.latest() == t_all[-1]


def test_a_readers_view_stays_valid_while_samples_are_added_and_moved():
    buf = JointBuffer(seconds=1000.0)
    buf.add(np.arange(10.0), np.ones((10, 6)))
    view_t, view_q = buf._t, buf._q                     # what at() holds outside the lock
    before_t, before_q = view_t.copy(), view_q.copy()
    for k in range(1, 400):                            # past the capacity: the rows move to new arrays
        buf.add(10.0 + k + np.arange(5) / 5, np.full((5, 6), float(k)))
    np.testing.assert_array_equal(view_t, before_t)
    np.testing.assert_array_equal(view_q, before_q)
    assert len(buf._t) == 10 + 399 * 5


def test_no_samples_yet_and_an_empty_batch():
    buf = JointBuffer()
    assert buf.latest() is None
    buf.add(np.empty(0), np.empty((0, 6)))
    assert buf.at(1.0) == (None, "no joint samples yet")
