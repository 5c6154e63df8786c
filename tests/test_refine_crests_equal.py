"""The refinement's numba path equals the numpy reference on the eight CT crests (issue 35): every
refinement call of a short replay of each crest (the seeded first frame's and the track's), run on
both backends (scripts/refine_calls.py). Slow: CI skips it (``-m slow`` runs it)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from tests.conftest import PELVIS_DIR

ROOT = Path(__file__).resolve().parents[1]
CRESTS = sorted(PELVIS_DIR.glob("crest_*.ply"))


def _script():
    spec = importlib.util.spec_from_file_location("refine_calls", ROOT / "scripts" / "refine_calls.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize("crest", [c.stem for c in CRESTS] or ["(none)"])
def test_numba_refinement_equals_numpy_on_a_ct_crest(crest, tmp_path_factory):
    """The pose within 0.01 mm (the issue's bound; measured: under 1e-12 mm), H and the template's
    predicted error to 1e-9 relative, the counts and shares the status uses exactly equal, the noise
    statistics to rounding."""
    if not CRESTS:
        pytest.skip(f"no CT crests in {PELVIS_DIR}")
    cache = tmp_path_factory.getbasetemp() / "refine_crests_equal"
    rows = _script().main(["--crests", crest, "--seconds", "0.3", "--frames", "6", "--repeats", "1",
                           "--cache", str(cache)])
    (row,) = rows
    diff = row["numba"]
    assert row["calls"] > 10
    assert diff["pose_mm"] < 0.01
    assert diff["H_rel"] < 1e-9 and diff["template_std_rel"] < 1e-9
    assert all(diff[k] == 0 for k in ("used", "expected", "confirmed", "stride", "converged"))
    assert diff["fitness"] == 0 and diff["sharp"] == 0 and diff["behind"] == 0
    for name in ("behind_allowed", "noise", "correlation", "rms"):
        assert diff[name] < 1e-9, name
