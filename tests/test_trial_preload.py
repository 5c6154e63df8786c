"""A recorded trial played as a live camera decodes its frames once, ahead, within a memory budget
(app/trial/preload.py; issue 35: a PNG decode per frame took close to half of one of the sandbox's two
cores from the tracker in a live session, BENCHMARKS.md "The live session").

Work is counted (PNG decodes), never timed."""
from __future__ import annotations

import numpy as np
import pytest

from app.errors import ConfigError, TrialFormatError
from app.image_streams import ImageStreams, InfraredStream
from app.trial.preload import frame_bytes, preload
from app.trial.reader import TrialReader, open_trial
from plugins.trial_player import RecordedCamera, SimulatedCamera
from tests.clocks import ManualClock
from tests.test_trial_images import color_stream, write_images_trial


@pytest.fixture
def trial(tmp_path):
    rng = np.random.default_rng(7)
    out, _, _ = write_images_trial(tmp_path, rng, ImageStreams(InfraredStream(emitter=True), color_stream(rng)), n=6)
    return out


def _count_decodes(monkeypatch) -> list[int]:
    calls: list[int] = []
    real = TrialReader.read_depth_png

    def counted(self, index):
        calls.append(index)
        return real(self, index)

    monkeypatch.setattr(TrialReader, "read_depth_png", counted)
    return calls


def test_preloaded_frames_are_bit_identical_to_the_readers(trial):
    reader = open_trial(trial)
    loaded = preload(open_trial(trial), budget_mb=64)
    assert loaded.count == 6
    for i in range(6):
        a, b = reader.read_depth(i), loaded.read_depth(i)
        assert a.dtype == b.dtype == np.float32
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(reader.read_infrared(i), loaded.read_infrared(i))
        np.testing.assert_array_equal(reader.read_color(i), loaded.read_color(i))
    assert loaded.meta.camera == reader.meta.camera and loaded.path == reader.path
    assert list(loaded.frame_ids) == list(reader.frame_ids)


def test_the_budget_bounds_how_many_frames_are_kept_and_the_others_decode_when_played(trial, monkeypatch):
    reader = open_trial(trial)
    one = frame_bytes(reader.meta)
    budget_mb = 3.5 * one / 2**20                      # room for three frames and a half: three
    loaded = preload(reader, budget_mb)
    assert loaded.count == 3
    assert loaded.megabytes * 2**20 <= budget_mb * 2**20
    calls = _count_decodes(monkeypatch)
    for i in range(6):
        loaded.read_depth(i)
    assert calls == [3, 4, 5]                         # only the frames beyond the budget are decoded
    assert preload(reader, 0) is reader               # 0: no preload at all


def test_a_corrupt_frame_ends_the_preload_and_fails_where_it_is_played(trial):
    reader = open_trial(trial)
    bad = trial / "depth" / f"{int(reader.frame_ids[4]):06d}.png"
    bad.write_bytes(b"not a png")
    loaded = preload(open_trial(trial), budget_mb=64)    # opening is not where it fails
    assert loaded.count == 4
    np.testing.assert_array_equal(loaded.read_depth(3), reader.read_depth(3))
    with pytest.raises(TrialFormatError, match="cannot be read as a PNG"):
        loaded.read_depth(4)


def test_a_player_with_its_trial_preloaded_decodes_no_png_while_it_plays(trial, monkeypatch):
    clock = ManualClock()
    camera = RecordedCamera(str(trial))
    calls = _count_decodes(monkeypatch)
    camera.open(clock, lambda *a: None)
    assert len(calls) == 6                             # decoded once, before the session's clock starts
    pushed = []
    camera.start(pushed.append)
    assert camera.finished.wait(10)
    camera.stop()
    assert len(calls) == 6 and camera.pushed == len(pushed) > 0
    reader = open_trial(trial)
    for frame in pushed:
        i = list(reader.frame_ids).index(frame.frame_id)
        np.testing.assert_array_equal(frame.depth_m, reader.read_depth(i))
        np.testing.assert_array_equal(frame.infrared, reader.read_infrared(i))


def test_a_player_without_a_preload_decodes_as_it_plays(trial, monkeypatch):
    camera = RecordedCamera(str(trial), preload_mb=0)
    calls = _count_decodes(monkeypatch)
    camera.open(ManualClock(), lambda *a: None)
    assert calls == []


@pytest.mark.parametrize("value", [-1, float("nan"), "lots", True, None])
def test_a_wrong_preload_budget_names_its_key(value):
    with pytest.raises(ConfigError, match=r"camera\.params\.preload_mb.*number >= 0"):
        RecordedCamera("unused", preload_mb=value)
    with pytest.raises(ConfigError, match=r"camera\.params\.preload_mb"):
        SimulatedCamera(preload_mb=value)
