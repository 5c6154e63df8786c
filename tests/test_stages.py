"""The tracker's stages over two cores (``filter.stages``, app/pipeline/stages.py; issue 35, deliver 2).

The parallel stages must not change a replay: ``estimate.txt`` and ``status.csv`` byte for byte the
same as serial's, on a trial with a hand over the bone (static_occluded: the refined track, its
nearby search every 10 frames, frames it does not weigh). The parallel run must also have used the
worker (the track's refinement beside the filter's step, the nearby search's fits in pairs): an
identity that held only because nothing ran in parallel would prove nothing.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from app.cli import main
from app.config import load_config
from app.errors import ConfigError
from app.pipeline import stages
from app.pipeline.stages import StageWorker, stages_mode


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """A 1 s static_occluded trial replayed with filter.stages serial and parallel (50 particles, cpu
    backend, the nearby search's work two fits a frame so that it runs them in pairs; the default, one,
    runs them on the loop), and which threads made the parallel run's track refinements and nearby fits."""
    from app.filter import refine_track
    from app.filter.refine_track import RefinedTrack

    base = tmp_path_factory.mktemp("stages")
    trial = base / "trial"
    assert main(["simulate", "--out", str(trial), "--seconds", "1.0", "--seed", "3"]) == 0
    out, threads = {}, {"track_fit": [], "scored_fit": []}
    track_fit, scored_fit = RefinedTrack.track_fit, RefinedTrack._scored_fit

    def spy(name, fn):
        def wrapped(*args, **kwargs):
            threads[name].append(threading.current_thread().name)
            return fn(*args, **kwargs)
        return wrapped

    for mode in ("serial", "parallel"):
        config = base / f"{mode}.yaml"
        config.write_text(f"filter:\n  particles: 50\n  stages: {mode}\nrender:\n  backend: cpu\n"
                          "refine:\n  nearby_per_frame: 2\n")   # two a frame: the search's fits in pairs
        out[mode] = base / mode
        if mode == "parallel":
            RefinedTrack.track_fit, RefinedTrack._scored_fit = spy("track_fit", track_fit), spy("scored_fit", scored_fit)
        try:
            assert main(["replay", str(trial), "--out", str(out[mode]), "--config", str(config), "--no-rrd",
                         "--no-projector"]) == 0
        finally:
            refine_track.RefinedTrack.track_fit, refine_track.RefinedTrack._scored_fit = track_fit, scored_fit
    return out, threads


@pytest.mark.parametrize("name", ["estimate.txt", "status.csv"])
def test_parallel_stages_give_the_serial_replay_byte_for_byte(replays, name):
    out, _ = replays
    serial, parallel = (out["serial"] / name).read_bytes(), (out["parallel"] / name).read_bytes()
    assert len(serial.splitlines()) > 80
    a, b = serial.splitlines(), parallel.splitlines()
    first = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), None)
    assert serial == parallel, f"{name} differs from line {first} (serial {len(a)} rows, parallel {len(b)})"


def test_the_parallel_replay_ran_its_refinements_on_the_worker(replays):
    _, threads = replays
    on_worker = [t for t in threads["track_fit"] if t.startswith("osteonav-stage")]
    assert len(on_worker) > 50                             # the track's refinement beside the filter's step
    assert any(t.startswith("osteonav-stage") for t in threads["scored_fit"])     # the nearby search's pairs
    assert any(not t.startswith("osteonav-stage") for t in threads["scored_fit"])


def test_a_wrong_stages_value_is_a_config_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("filter:\n  stages: threads\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "filter.stages" in str(err.value) and "serial" in str(err.value) and "parallel" in str(err.value)
    with pytest.raises(ValueError, match="filter.stages"):
        stages_mode("threads", True)


def test_auto_is_parallel_on_two_cores_with_the_refinement(monkeypatch):
    assert load_config(None).stages == "auto"                   # the default since measured faster on an idle 2-core machine
    monkeypatch.setattr(stages, "usable_cores", lambda: 2)
    assert stages_mode("auto", True) == "parallel"
    assert stages_mode("auto", False) == "serial"              # nothing to overlap without the refinement
    assert stages_mode("parallel", False) == "serial"
    assert stages_mode("serial", True) == "serial"
    monkeypatch.setattr(stages, "usable_cores", lambda: 1)
    assert stages_mode("auto", True) == "serial"
    assert stages_mode("parallel", True) == "parallel"         # asked for: honoured


def test_pairs_keeps_the_order_and_waits_for_a_fit_it_drops():
    worker = StageWorker()
    try:
        assert list(worker.pairs(lambda x: x * x, range(5))) == [0, 1, 4, 9, 16]
        assert list(worker.pairs(lambda x: x, [])) == []
        finished = []

        def slow(x):
            time.sleep(0.05 if x == 1 else 0.0)
            finished.append(x)
            return x

        for value in worker.pairs(slow, [0, 1, 2, 3]):
            if value == 0:
                break                                          # the consumer stops at the first
        assert finished == [0, 1]                              # item 1 (on the worker) was waited for; 2, 3 never ran

        def fails(x):
            if x == 3:
                raise RuntimeError("fit 3")
            return x

        got = []
        with pytest.raises(RuntimeError, match="fit 3"):
            for value in worker.pairs(fails, [0, 1, 2, 3, 4]):
                got.append(value)
        assert got == [0, 1, 2]                                # as map would have raised: after 2, at 3
    finally:
        worker.close()
