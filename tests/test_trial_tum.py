"""TUM trajectory files (quaternion scalar last, as evo reads them) and status.csv."""
from __future__ import annotations

import numpy as np
import pytest

from app.errors import TrialFormatError
from app.geometry import quaternion as quat
from app.geometry import se3
from app.trial.tum import read_status_csv, read_tum, write_status_csv, write_tum


def test_tum_round_trip_to_nine_decimals(tmp_path, rng):
    n = 20
    stamps = 100.0 + np.cumsum(rng.uniform(0.01, 0.05, n))
    T = se3.from_quat_trans(quat.random_uniform(rng, n), rng.uniform(-1, 1, (n, 3)))
    write_tum(tmp_path / "traj.txt", stamps, T)
    stamps2, T2 = read_tum(tmp_path / "traj.txt")
    np.testing.assert_allclose(stamps2, stamps, atol=1e-9)
    np.testing.assert_allclose(T2, T, atol=1e-8)


def test_tum_row_is_translation_then_quaternion_scalar_last(tmp_path):
    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    T = se3.from_quat_trans(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]), np.array([0.1, -0.2, 0.3]))
    write_tum(tmp_path / "t.txt", [12.5], T[None])
    header, row = (tmp_path / "t.txt").read_text().splitlines()
    assert header == "# stamp tx ty tz qx qy qz qw"
    values = [float(v) for v in row.split()]
    np.testing.assert_allclose(values, [12.5, 0.1, -0.2, 0.3, 0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=1e-9)
    assert row.split()[0] == "12.500000000"


def test_read_tum_accepts_six_decimals_and_comments(tmp_path):
    (tmp_path / "t.txt").write_text("# from evo\n\n12.000000 0.612 -0.118 0.041 0.0 0.0 0.0 1.0\n"
                                    "12.033333 0.612 -0.118 0.041 0.0 0.0 0.707107 0.707107\n")
    stamps, T = read_tum(tmp_path / "t.txt")
    assert stamps.tolist() == [12.0, 12.033333]
    np.testing.assert_allclose(T[1][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    assert se3.is_rigid(T[1])


@pytest.mark.parametrize("row, message", [
    ("13.0 0 0 0 0 0 0", "expected 8 values"),
    ("13.0 0 0 0 0 0 0 x", "expected numbers"),
    ("13.0 0 nan 0 0 0 0 1", "finite"),
    ("13.0 0 0 0 0 0 0 0.5", "unit norm"),
    ("11.0 0 0 0 0 0 0 1", "increase strictly"),
])
def test_read_tum_errors_name_the_line(tmp_path, row, message):
    path = tmp_path / "t.txt"
    path.write_text(f"# stamp tx ty tz qx qy qz qw\n12.0 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(TrialFormatError, match=f"t.txt \\(line 3\\): .*{message}"):
        read_tum(path)


def test_status_csv_round_trip_and_rejects_unknown_status(tmp_path):
    write_status_csv(tmp_path / "status.csv", [1.0, 2.0, 3.0], ["ok", "uncertain", "lost"])
    assert (tmp_path / "status.csv").read_text().splitlines()[:2] == ["stamp,status", "1.000000000,ok"]
    stamps, statuses = read_status_csv(tmp_path / "status.csv")
    assert stamps.tolist() == [1.0, 2.0, 3.0] and statuses == ["ok", "uncertain", "lost"]
    with pytest.raises(ValueError, match="unknown status \\['fine'\\]"):
        write_status_csv(tmp_path / "s2.csv", [1.0], ["fine"])
