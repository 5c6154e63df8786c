"""Tracking on the real CT crest meshes of ../shared/data/pelvis (not the default synthetic crest).

Each crest is simulated (app/sim, scenario ``static_clear``: a static bone, a moving camera) and
replayed with the product's default configuration; the errors are against the simulated ground
truth. The safety rule holds on every frame of every crest: no frame ``ok`` while ADD > 5 mm.
The accuracy bound, ADD median < 1 mm and no frame lost (ADD > 10 mm) after the first 0.5 s,
leaves the filter half a second to converge from the 5 mm / 3 deg initial error. Measured
2026-11-24 with the local refinement on (default; 4 s, seeds 0 and 1, all 16 runs, printed with -s):
ADD median 0.14-0.58 mm (median of the runs 0.19 mm, worst crest_right_03 seed 1), p95 0.20-0.78 mm,
max 6.3 mm (crest_left_05 seed 1, not ok then), ok on 87 % of the frames, 0 frames ok while > 5 mm
off. Before the refinement (filter alone) the medians were 0.8-2.9 mm and crest_right_02 seed 0 had
35 frames ok while > 5 mm off.

The full run (every crest, 4 s each) is slow (``-m slow``); CI runs one crest for 1 s.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM

PELVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pelvis"
CRESTS = sorted(PELVIS.glob("crest_*.ply")) if PELVIS.is_dir() else []
SETTLE_S = 0.5
MEDIAN_ADD_MM = 1.0


def _track(mesh: Path, tmp_path: Path, seconds: float, seed: int, scenario: str = "static_clear"):
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", mesh_path=mesh, scenario_name=scenario, seconds=seconds, seed=seed)
    result = replay(tmp_path / "trial", tmp_path / "out", load_config(None), rrd=False, projector=False)
    add = np.asarray(result.errors["add_mm"])
    statuses = np.asarray(result.statuses)
    t = np.asarray(result.stamps) - result.stamps[0]
    print(f"\n{mesh.stem} {scenario} seed {seed}: {len(add)} frames, ADD median {np.median(add):.2f} mm, p95 "
          f"{np.percentile(add, 95):.2f}, max {add.max():.2f}; ok {np.mean(statuses == 'ok'):.0%}; "
          f"dangerous {int(np.sum((statuses == 'ok') & (add > DANGEROUS_ADD_MM)))}")
    return add, statuses, t


def _check(add: np.ndarray, statuses: np.ndarray, t: np.ndarray) -> None:
    dangerous = (statuses == "ok") & (add > DANGEROUS_ADD_MM)
    assert not dangerous.any(), f"{dangerous.sum()} frames ok while > 5 mm off: {add[dangerous].round(2)}"
    assert np.median(add) < MEDIAN_ADD_MM
    settled = t >= SETTLE_S
    assert not np.any(add[settled] > LOST_ADD_MM), f"lost after {SETTLE_S} s: max ADD {add[settled].max():.1f} mm"


@pytest.mark.skipif(not CRESTS, reason=f"no CT crest meshes at {PELVIS}")
def test_one_ct_crest_is_tracked_safely(tmp_path):
    """CI's short version: the first crest, 1 s."""
    _check(*_track(CRESTS[0], tmp_path, seconds=1.0, seed=0))


@pytest.mark.slow
@pytest.mark.skipif(not CRESTS, reason=f"no CT crest meshes at {PELVIS}")
@pytest.mark.parametrize("mesh", CRESTS, ids=[m.stem for m in CRESTS])
@pytest.mark.parametrize("seed", [0, 1])
def test_every_ct_crest_is_tracked_safely(mesh, seed, tmp_path):
    _check(*_track(mesh, tmp_path, seconds=4.0, seed=seed))


@pytest.mark.slow
@pytest.mark.skipif(not CRESTS, reason=f"no CT crest meshes at {PELVIS}")
@pytest.mark.parametrize("mesh", CRESTS, ids=[m.stem for m in CRESTS])
def test_every_ct_crest_is_back_within_1mm_0_3s_after_the_bone_comes_to_rest(mesh, tmp_path):
    """Issue 12's moving-bone target (bone_moves: 5 cm and 30 deg at up to ~5 cm/s, at rest from 3.5 s):
    ADD < 1 mm on every frame from 0.3 s after rest. Measured (BENCHMARKS.md §6, 4.5 s, seed 0, b8db850):
    max ADD after rest + 0.3 s 0.26-0.89 mm over the eight crests, 0 frames ok while > 5 mm off."""
    add, statuses, t = _track(mesh, tmp_path, seconds=4.5, seed=0, scenario="bone_moves")
    assert not np.any((statuses == "ok") & (add > DANGEROUS_ADD_MM))
    late = t >= 3.5 + 0.3
    assert late.sum() > 30 and add[late].max() < 1.0, f"max ADD after rest + 0.3 s: {add[late].max():.2f} mm"


# the known gap (BENCHMARKS.md "Residual tissue: the fit the tissue pulls"): on crest_right_02 the tissue
# moves the cost's minimum itself, 1.2-1.3 mm off; no nearby fit explains the image better, the predicted
# template std is 0.87-0.97 mm (below the 1 mm tolerance) and the behind excess 0.001 (the noise bound 0.002
# since the correlation correction, 99d4bb4, which issue 32 asked for). strict: the day it passes, say so.
TISSUE_GAP = {"crest_right_02": "ok on 63-65 % of the frames 1.2-1.3 mm off under residual tissue (known gap, "
                                "within issue 32's 2 mm, outside the 1 mm tolerance)"}


@pytest.mark.slow
@pytest.mark.skipif(not CRESTS, reason=f"no CT crest meshes at {PELVIS}")
@pytest.mark.parametrize("mesh", [pytest.param(m, marks=pytest.mark.xfail(strict=True, reason=TISSUE_GAP[m.stem]))
                                  if m.stem in TISSUE_GAP else m for m in CRESTS], ids=[m.stem for m in CRESTS])
def test_under_residual_tissue_the_status_is_rarely_ok_while_off(mesh, tmp_path):
    """or_deep_tissue (3 mm tissue on a third of the ridge): the refined fit ends 1.1-2.3 mm off; before
    the behind-the-model rule it was ok on 89-93 of 134 frames per crest while > 1 mm off; with the fixed
    2 % share 0-14 (BENCHMARKS.md §6), with the noise bound (status.max_behind_excess) 0-1 (§6d).
    The fits 0.5-1 mm off sat on a plateau of the refinement's cost and were ok on 1-76 % of the
    frames of crest_left_03 and crest_left_04 (3 s runs, §6i); the search for a competitor near the
    track (refine.nearby_*, §6j) finds a fit > 1 mm away explaining the image better there.
    Asserted: never ok while > 2 mm off (issue 32's target), ok while > 1 mm off on at most 15 % of the
    frames, and ok while 0.5-1 mm off on at most 5 % (the plateau). Measured 2026-11-28 (main 6a48198):
    ok while > 1 mm off on 0-2.2 % of the frames of seven crests, never > 2 mm; crest_right_02 is the
    known gap (TISSUE_GAP: 14.9 % before 99d4bb4, 63-65 % since)."""
    add, statuses, t = _track(mesh, tmp_path, seconds=1.5, seed=0, scenario="or_deep_tissue")
    ok = statuses == "ok"
    assert not np.any(ok & (add > 2.0)), f"ok while > 2 mm off: {add[ok & (add > 2.0)].round(2)}"
    assert np.mean(ok & (add > 1.0)) <= 0.15, f"ok while > 1 mm off on {np.mean(ok & (add > 1.0)):.0%} of the frames"
    plateau = ok & (add > 0.5) & (add <= 1.0)
    assert np.mean(plateau) <= 0.05, f"ok while 0.5-1 mm off on {np.mean(plateau):.0%} of the frames"


@pytest.mark.slow
@pytest.mark.skipif(not (PELVIS / "crest_left_02.ply").is_file(), reason=f"no crest_left_02 at {PELVIS}")
def test_the_plateau_beyond_a_better_fit_within_1mm_is_not_ok(tmp_path):
    """crest_left_02 in or_model_mismatch (seed 0, 3.5 s as in the bench's matrix): the first frames the
    other rules let be ok lay 1.0-1.2 mm off, the template's outline up to 3.0 mm (BENCHMARKS.md §6k);
    the nearby search's follow-ups (refine.nearby_followups) once kept them below ok. Since the status's
    correlation correction and the competitor's validation the scene is never ok while > 1 mm off without
    them (2026-11-28: 0 frames with and without), and issue 32 removed them. Asserted: 0 frames ok while
    more than 1 mm off."""
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", mesh_path=PELVIS / "crest_left_02.ply", scenario_name="or_model_mismatch",
             seconds=3.5, seed=0)
    result = replay(tmp_path / "trial", tmp_path / "out", load_config(None), rrd=False, projector=False)
    add, ok = np.asarray(result.errors["add_mm"]), np.asarray(result.statuses) == "ok"
    off = int(np.sum(ok & (add > 1.0)))
    assert off == 0, f"{off} frames ok while > 1 mm off: {add[ok & (add > 1.0)].round(2)}"


@pytest.mark.slow
@pytest.mark.skipif(not CRESTS, reason=f"no CT crest meshes at {PELVIS}")
@pytest.mark.parametrize("mesh", CRESTS, ids=[m.stem for m in CRESTS])
def test_every_ct_crest_at_0_65_m_is_precise_and_mostly_ok(mesh, tmp_path):
    """static_far (the bone 0.65 m away, ~1.6k of 307k pixels), seed 0, 1.5 s: refined at stride 1 and
    judged by the noise-bound behind rule (BENCHMARKS.md §6d: ADD median 0.16-0.25 mm, ok on 99-100 %
    of the frames after 0.5 s on the eight crests; before, at stride 2 with the fixed 2 % share, 0.32-0.99
    mm and ok on 0-64 %). Asserted: ADD median < 0.5 mm, ok on > 80 % of the frames after 0.5 s, never
    ok while > 5 mm off."""
    add, statuses, t = _track(mesh, tmp_path, seconds=1.5, seed=0, scenario="static_far")
    ok = statuses == "ok"
    assert not np.any(ok & (add > DANGEROUS_ADD_MM))
    assert np.median(add) < 0.5
    assert ok[t >= SETTLE_S].mean() > 0.8, f"ok on {ok[t >= SETTLE_S].mean():.0%} of the frames after {SETTLE_S} s"
