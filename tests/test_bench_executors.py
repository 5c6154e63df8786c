"""``osteonav bench --executor local|ray``: the same rows from a Ray cluster as from this machine,
trials shipped to a worker that does not see them, and the options' refusals."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from app.bench import bench, bundles
from app.bench.ray_executor import run_remote

TRIAL_SECONDS = 0.5
TIMING_KEYS = ("fps", "wall_s", "timings_ms")
TINY = "filter:\n  particles: 40\nrender:\n  resolution: [40, 30]\n  mesh_triangles: 300\n"


def _comparable(row: dict, keep_path: bool = False) -> str:
    """The row without its timings, its backend's thread count and (unless ``keep_path``) its
    trial path, as JSON text (NaN equal to NaN)."""
    import re

    kept = {k: v for k, v in row.items() if k not in TIMING_KEYS + (() if keep_path else ("trial_path",))}
    kept["gl"] = re.sub(r"\d+ threads", "N threads", kept.get("gl") or "")
    return json.dumps(kept, sort_keys=True)


@pytest.fixture(scope="module")
def trial(tmp_path_factory) -> Path:
    from app.sim.simulator import DEFAULT_MESH, simulate

    out = tmp_path_factory.mktemp("executors") / "static_clear"
    simulate(out, DEFAULT_MESH, "static_clear", seconds=TRIAL_SECONDS, seed=0)
    return out


@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


# --------------------------------------------------------------------------- options

def test_executor_ray_without_ray_says_how_to_install_it(monkeypatch, tmp_path, tiny, capsys):
    from app.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)   # `import ray` raises ImportError
    out_json = tmp_path / "bench.json"
    rc = main(["bench", "--executor", "ray", "--configs", str(tiny), "--json", str(out_json)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "--executor" in err[0] and "pip install -e '.[ray]'" in err[0]
    assert not out_json.exists()


@pytest.mark.parametrize("argv, key", [(["--address", "auto"], "--address"), (["--task-memory", "2"], "--task-memory"),
                                       (["--executor", "ray", "--jobs", "2"], "--jobs")])
def test_ray_options_are_refused_where_they_do_not_apply(tmp_path, tiny, capsys, argv, key):
    from app.cli import main

    rc = main(["bench", *argv, "--configs", str(tiny), "--json", str(tmp_path / "b.json")])
    err = capsys.readouterr().err
    assert rc == 2 and f"'{key}'" in err and "Traceback" not in err


# --------------------------------------------------------------------------- bundles

def test_a_packed_trial_unpacks_to_the_same_fingerprint_and_an_edit_changes_it(trial, tmp_path):
    key = bundles.fingerprint(trial)
    copy = bundles.unpack(bundles.pack(trial), tmp_path / "copy")
    assert bundles.fingerprint(copy) == key
    assert sorted(p.relative_to(copy) for p in copy.rglob("*")) == sorted(p.relative_to(trial) for p in trial.rglob("*"))
    (copy / "groundtruth.txt").write_text((copy / "groundtruth.txt").read_text() + "\n")
    assert bundles.fingerprint(copy) != key
    shutil.rmtree(copy / "depth")
    (copy / "depth").mkdir()
    assert bundles.fingerprint(copy) != key
    assert bundles.fingerprint(tmp_path / "nothing") is None


def test_a_worker_that_does_not_see_the_trial_asks_for_it_then_runs_the_shipped_copy(trial, tiny, tmp_path,
                                                                                       monkeypatch):
    """run_remote (a Ray task's body, called here in this process): the trial's path missing or
    holding another trial is "missing"; with the packed trial it runs on the copy unpacked in the
    node's cache, and its row is the local run's but for timings (trial_path the driver's)."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "node_tmp"))
    (tmp_path / "node_tmp").mkdir()
    config = bench.resolve_configs([str(tiny)])[0]
    key = bundles.fingerprint(trial)
    elsewhere = bench.TrialSpec(str(tmp_path / "not_here"), "iliac_crest", "static_clear", frames=1)
    task = {"config": config, "trial": elsewhere, "out_dir": "runs/x", "with_vsd": False}
    assert run_remote(task, key)["missing"] == elsewhere.path
    stale = bench.TrialSpec(str(trial), "iliac_crest", "static_clear")
    assert "missing" in run_remote({**task, "trial": stale}, "0" * 40)

    result = run_remote(task, key, bundles.pack(trial))
    assert bundles.fingerprint(bundles.node_cache() / key) == key
    local = bench.run_one(config, bench.TrialSpec(str(trial), "iliac_crest", "static_clear"), with_vsd=False)
    assert result["row"]["trial_path"] == elsewhere.path
    assert _comparable(result["row"]) == _comparable(local)
    outputs = bundles.unpack(result["out"], tmp_path / "out")
    assert (outputs / "estimate.txt").is_file() and (outputs / "status.csv").is_file()


# --------------------------------------------------------------------------- a local Ray instance

def test_ray_executor_gives_the_local_rows_and_simulates_the_same_trials(tmp_path, tiny, monkeypatch):
    """`osteonav bench` with --executor local and --executor ray (a Ray instance started for the
    bench), each in a folder of its own with the same relative --cache, --json and --out, on one
    0.5 s scenario: identical rows but for timings (and the thread count the backend names: a Ray
    run has 1 CPU), trial paths included; identical simulated trials, the ray run's trial reusable
    from its cache, and its --out files where a local run puts them."""
    pytest.importorskip("ray")
    from app.cli import main
    from app.sim.simulator import DEFAULT_MESH

    common = ["bench", "--configs", str(tiny), "--scenarios", "static_clear", "--seconds", str(TRIAL_SECONDS),
              "--meshes", str(DEFAULT_MESH), "--seeds", "0", "--no-vsd", "--cache", "cache", "--json", "b.json",
              "--out", "out"]
    runs = {}
    for name in ("local", "ray"):
        (tmp_path / name).mkdir()
        monkeypatch.chdir(tmp_path / name)
        assert main([*common, "--executor", name]) == 0, name
        runs[name] = json.loads((tmp_path / name / "b.json").read_text())
    assert runs["ray"]["meta"]["executor"] == "ray" and runs["ray"]["meta"]["cluster"]["cpus"] >= 1
    assert [_comparable(r, keep_path=True) for r in runs["ray"]["rows"]] == \
        [_comparable(r, keep_path=True) for r in runs["local"]["rows"]]
    assert len(runs["ray"]["rows"]) == 1 and "partial" not in runs["ray"]["meta"]
    assert runs["ray"]["rows"][0]["trial_path"] == str(Path("cache") / DEFAULT_MESH.stem / "static_clear")
    gl = runs["ray"]["rows"][0]["gl"] or ""
    assert "threads" not in gl or "1 threads" in gl   # a run's numba threads are its 1 CPU
    trials = {name: tmp_path / name / "cache" / DEFAULT_MESH.stem / "static_clear" for name in runs}
    assert bundles.fingerprint(trials["ray"]) == bundles.fingerprint(trials["local"]) is not None
    again = bench.standard_trials(tmp_path / "ray" / "cache", ["static_clear"], TRIAL_SECONDS, [DEFAULT_MESH],
                                  seeds=[0], lazy=True, progress=False)
    assert again[0].simulation is None   # the cache is valid: a second bench does not simulate again
    run_out = Path("out") / "tiny" / DEFAULT_MESH.stem / "static_clear" / "estimate.txt"
    assert (tmp_path / "ray" / run_out).read_text() == (tmp_path / "local" / run_out).read_text()


# --------------------------------------------------------------------------- the partial matrix

def test_partial_json_writes_after_every_run_while_writing_stays_under_its_share():
    """A manual clock: each write takes 1/8 s per row; runs finish every 1 s. With share 1/8, a
    write of w s starting at t is followed by no other before t + 8 w: the first two runs are
    written each, then the gaps grow with the rows (here they double), and the writes take at
    most an eighth of the time."""
    from app.bench.partial import PartialJson

    now = [0.0]
    written = []

    def write(rows, path, meta):
        assert meta["partial"] is True and meta["planned_runs"] == 40 and path == "b.json"
        written.append((now[0], len(rows)))
        now[0] += 0.125 * len(rows)

    partial = PartialJson("b.json", {"planned_runs": 40}, share=0.125, clock=lambda: now[0], write=write)
    rows = []
    for k in range(40):
        now[0] = max(now[0], float(k))   # run k finishes at k s (or when the last write ended)
        rows.append({"run": k})
        partial(rows)
    assert written == [(0.0, 1), (1.0, 2), (3.0, 4), (7.0, 8), (15.0, 16), (31.0, 32)]
    assert sum(0.125 * n for _, n in written) <= 0.125 * (written[-1][0] + 8 * 0.125 * written[-1][1])


def test_osteonav_errors_survive_pickling_so_a_worker_can_raise_them():
    """A run in a spawned process or a Ray task raises in the worker; the driver unpickles the error."""
    import pickle

    from app.errors import ConfigError, TrialFormatError

    for exc in (ConfigError("filter.particles", "expected > 0, got -1", "my.yaml"),
                TrialFormatError("trial/frames.csv", "bad row", "line 3")):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc)
    assert pickle.loads(pickle.dumps(ConfigError("k", "m"))).key == "k"


@pytest.mark.parametrize("address, says", [("127.0.0.1:1", "no Ray cluster answers at 127.0.0.1:1"),
                                           ("headnode", "expected auto or HOST:PORT")])
def test_an_address_without_a_cluster_is_refused_at_once(address, says):
    """ray.init would retry an unreachable head for minutes; the bench says so in one line instead."""
    from app.bench.ray_executor import _check_reachable
    from app.errors import ConfigError

    with pytest.raises(ConfigError, match="--address") as info:
        _check_reachable(address, timeout_s=2.0)
    assert says in str(info.value)


def test_unpacking_a_run_s_outputs_keeps_what_the_folder_already_holds(tmp_path):
    """The driver unpacks a Ray run's output folder with replace=False: files there stay."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "estimate.txt").write_text("new")
    dest = tmp_path / "dest"
    dest.mkdir()
    (dest / "notes.txt").write_text("mine")
    (dest / "estimate.txt").write_text("old")
    bundles.unpack(bundles.pack(src), dest, replace=False)
    assert (dest / "notes.txt").read_text() == "mine" and (dest / "estimate.txt").read_text() == "new"


@pytest.mark.parametrize("text", ["0", "-1", "nan", "inf", "x"])
def test_task_memory_is_checked_at_parse_time(text, capsys):
    from app.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["bench", "--executor", "ray", "--task-memory", text])
    assert exc.value.code == 2 and "--task-memory" in capsys.readouterr().err
