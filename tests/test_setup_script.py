"""scripts/setup.sh: the system-library check reports exactly the missing libraries, every time.

Its first version piped ``ldconfig -p`` into ``grep -q`` under ``set -o pipefail``: grep exits at its
first match, ldconfig dies of SIGPIPE and the pipeline failed, so a present library was reported
missing in about one run of six (34 of 200 for libusb). The check runs many times here.
"""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SETUP = Path(__file__).resolve().parents[1] / "scripts" / "setup.sh"
RUNS = 50

pytestmark = pytest.mark.skipif(shutil.which("ldconfig") is None, reason="no ldconfig (not a glibc Linux)")


def _cached_libraries() -> list[str]:
    """Names in the linker cache (``ldconfig -p``), read whole: no pipe."""
    out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, check=True).stdout
    return [line.split()[0] for line in out.splitlines()[1:] if line.startswith(("\t", " "))]


def _missing_libs_many_times(libs: list[str]) -> list[str]:
    """The script's ``missing_libs`` run ``RUNS`` times in one bash (the script sourced, so its
    ``set -euo pipefail`` is in force); one line per run: the names it reported missing."""
    script = f'source "{SETUP}"; for _ in $(seq {RUNS}); do echo "[$(missing_libs {" ".join(libs)} | tr "\\n" " ")]"; done'
    proc = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_present_libraries_are_never_reported_missing():
    cached = _cached_libraries()
    # the script's own list where this machine has it (CI does: the suite renders with Mesa's EGL),
    # and libraries every glibc system has: libc, libm, libpthread
    required = [lib for lib in ("libEGL.so.1", "libGL.so.1", "libEGL_mesa.so.0", "libusb-1.0.so.0") if lib in cached]
    present = required + [lib for lib in ("libc.so.6", "libm.so.6", "libpthread.so.0") if lib in cached]
    assert len(present) >= 2, cached[:20]
    runs = _missing_libs_many_times(present)
    assert runs == ["[]"] * RUNS


def test_an_absent_library_is_reported_missing_every_time_and_alone():
    present = _cached_libraries()[0]
    prefix = present[:-1]      # e.g. "libc.so." of "libc.so.6": a name must match whole, not as a prefix
    runs = _missing_libs_many_times([present, "libosteonav-absent.so.7", prefix])
    assert runs == [f"[libosteonav-absent.so.7 {prefix} ]"] * RUNS
