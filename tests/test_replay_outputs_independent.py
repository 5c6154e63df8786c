"""A replay's estimates do not depend on its outputs (issue 34, deliver 4).

``--no-projector`` used to change the tracking: with the projector the tracker's status bounded the
predicted error of the plan's template points, without it the mesh's vertices, and the statuses (and
with them the recovery and the estimates) parted from frame 127 of this trial. The tracker now gets
the plan's points whenever a plan is known. Each output option is switched off in turn and
``estimate.txt`` and ``status.csv`` must stay byte for byte the same.

Cheap on purpose: a 1.5 s trial (134 frames; the old code differed at frame 127), 50 particles, the
cpu backend.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from app.cli import main

VARIANTS = {
    "no-projector": ["--no-projector"],
    "no-rrd": ["--no-rrd"],
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The output folders of one replay with every output on and one per option switched off."""
    base = tmp_path_factory.mktemp("outputs")
    trial = base / "trial"
    assert main(["simulate", "--out", str(trial), "--seconds", "1.5", "--seed", "3"]) == 0
    config = base / "small.yaml"
    config.write_text("filter:\n  particles: 50\nrender:\n  backend: cpu\n")
    out = {}
    for name, extra in {"all": ["--projector-images"], **VARIANTS}.items():
        out[name] = base / name
        assert main(["replay", str(trial), "--out", str(out[name]), "--config", str(config), *extra]) == 0
    return out


def test_every_output_was_written_by_the_full_run(runs):
    full = runs["all"]
    assert (full / "log.rrd").stat().st_size > 0
    assert len(list((full / "projector").glob("*.png"))) > 0
    assert not (runs["no-projector"] / "projector").exists()
    assert not (runs["no-rrd"] / "log.rrd").exists()


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("name", ["estimate.txt", "status.csv"])
def test_estimates_and_statuses_do_not_depend_on_the_outputs(runs, variant, name):
    full = (runs["all"] / name).read_text().splitlines()
    other = (runs[variant] / name).read_text().splitlines()
    assert len(full) > 100
    first = next((i for i, (a, b) in enumerate(zip(full, other)) if a != b), None)
    assert first is None and len(full) == len(other), f"{name} differs from line {first} with --{variant}"
