"""Sensor models in simulated trials: ``simulate --sensor``, trial.yaml's ``sensor`` block, the bench's cache."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from app.cli import main
from app.sim.sensors import SENSORS, sensor_from_dict, sensor_to_dict
from app.sim.sensors.independent import IndependentSensor
from app.sim.sensors.stereo import StereoSensor
from app.sim.simulator import DEFAULT_MESH
from app.trial.reader import open_trial


@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    """The same scene (seed 1, 0.05 s) through the default model and the stereo model."""
    root = tmp_path_factory.mktemp("sensor_trials")
    args = ["--scenario", "static_clear", "--seconds", "0.05", "--seed", "1"]
    assert main(["simulate", "--out", str(root / "default"), *args]) == 0
    assert main(["simulate", "--out", str(root / "stereo"), "--sensor", "stereo", *args]) == 0
    return root


def test_simulate_sensor_stereo_writes_a_trial_that_reads_back_with_its_sensor(trials):
    reader = open_trial(trials / "stereo")
    assert sensor_from_dict(reader.meta.extra["sensor"]) == StereoSensor()
    info = yaml.safe_load((trials / "stereo" / "simulation.yaml").read_text())
    assert info["sensor"] == sensor_to_dict(StereoSensor())
    depth = next(iter(reader.iter_frames())).depth_m
    # the band on the image's left edge that the right imager cannot match (~d = f b / z >= 50 px wide)
    assert (depth[:, :40] == 0).all()
    default = next(iter(open_trial(trials / "default").iter_frames())).depth_m
    assert (default[:, :40] > 0).mean() > 0.9


def test_the_default_trial_names_the_independent_model_and_shares_the_scene_with_stereo(trials):
    """Only the depth differs between models: joints and ground truth of the same seed are byte-identical."""
    reader = open_trial(trials / "default")
    assert sensor_from_dict(reader.meta.extra["sensor"]) == IndependentSensor()
    for name in ("joints.csv", "groundtruth.txt", "frames.csv", "camera_truth.txt"):
        assert (trials / "default" / name).read_bytes() == (trials / "stereo" / name).read_bytes(), name


def test_simulate_refuses_an_unknown_sensor_with_the_list_before_writing(tmp_path, capsys):
    out = tmp_path / "trial"
    assert main(["simulate", "--out", str(out), "--sensor", "kinect"]) == 2
    err = capsys.readouterr().err
    assert f"--sensor: unknown sensor model 'kinect'; valid: {', '.join(SENSORS)}" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_bench_simulates_and_caches_each_sensor_model_under_its_own_name(tmp_path):
    from app.bench.trials import recorded_trials, standard_trials

    kwargs = dict(cache=tmp_path, scenarios=["static_clear"], seconds=0.03, meshes=[DEFAULT_MESH], lazy=True)
    specs = standard_trials(**kwargs, sensors=["independent", "stereo"])
    assert [(s.scenario, s.sensor) for s in specs] == [("static_clear", "independent"), ("static_clear@stereo", "stereo")]
    assert specs[1].path.endswith("iliac_crest/static_clear@stereo") and specs[0].path.endswith("iliac_crest/static_clear")
    specs[1].ensure()
    assert sensor_from_dict(open_trial(specs[1].path).meta.extra["sensor"]) == StereoSensor()
    again = standard_trials(**kwargs, sensors=["stereo"])
    assert again[0].simulation is None                 # cached: not simulated again
    assert recorded_trials([specs[1].path])[0].sensor == "stereo"
    with pytest.raises(ValueError, match="'--sensors'.*valid: independent, stereo, tof"):
        standard_trials(**kwargs, sensors=["kinect"])


def test_bench_cache_made_before_sensor_models_stays_valid_for_the_independent_model(tmp_path):
    """A simulation.yaml without 'sensor' was made by today's independent model with its defaults."""
    from app.bench.trials import _DEFAULT_SENSOR_DICT, standard_trials

    assert _DEFAULT_SENSOR_DICT == sensor_to_dict(IndependentSensor())
    kwargs = dict(cache=tmp_path, scenarios=["static_clear"], seconds=0.03, meshes=[DEFAULT_MESH], lazy=True)
    spec = standard_trials(**kwargs)[0]
    spec.ensure()
    info_path = tmp_path / "iliac_crest" / "static_clear" / "simulation.yaml"
    info = yaml.safe_load(info_path.read_text())
    del info["sensor"]
    info_path.write_text(yaml.safe_dump(info))
    assert standard_trials(**kwargs)[0].simulation is None
    assert standard_trials(**kwargs, sensors=["independent:k=0.002"])[0].simulation is not None


def test_a_session_simulated_source_takes_a_sensor_model(tmp_path):
    """``camera: simulated`` / ``robot: simulated`` with ``params: {sensor: ...}``: the trial they play is made
    by that model; an unknown one is refused when the session file is read, naming the key."""
    from app.errors import ConfigError
    from app.plugins_registry import create
    from plugins.trial_player import simulated_trial

    with pytest.raises(ConfigError, match=r"'camera.params.sensor'.*valid: independent, stereo, tof"):
        create("camera", "simulated", {"sensor": "kinect"})
    with pytest.raises(ConfigError, match=r"'robot.params.sensor'.*no parameter 'sigma'"):
        create("robot", "simulated", {"sensor": "tof:sigma=1"})
    assert create("camera", "simulated", {"sensor": "tof"})._sim[6] == "tof"         # (scenario, ..., streams, sensor, pointer)
    out = simulated_trial("static_clear", 0.03, 1, None, str(tmp_path / "t"), sensor="tof")
    assert open_trial(out).meta.extra["sensor"]["model"] == "tof"


def test_bench_refuses_an_unknown_sensor_or_sensors_with_recorded_trials_before_writing(tmp_path, capsys, trials):
    out = tmp_path / "bench.json"
    assert main(["bench", "--sensors", "stereo", "kinect", "--quick", "--json", str(out)]) == 2
    assert "'--sensors': unknown sensor model 'kinect'; valid: independent, stereo, tof" in capsys.readouterr().err
    assert main(["bench", "--sensors", "stereo", "--trials", str(trials / "stereo"), "--json", str(out)]) == 2
    assert "give --sensors or --trials, not both" in capsys.readouterr().err
    assert not out.exists() and list(tmp_path.iterdir()) == []
