"""The decision numbers: every number in configs/default.yaml that decides a frame's status (a reason
code) or a lifecycle transition, with its unit and how it was chosen (issue 32, Deliver 4).

Import as ``from app import decision_numbers``; ``python scripts/decision_numbers.py`` prints the table
that README.md shows ("Decision numbers"; tests/test_decision_numbers.py checks that it is current).

Each numeric key of ``status``, ``refine`` and ``recovery`` ends its comment in configs/default.yaml
with its kind in brackets:

- ``[status, UNIT: how chosen]``: decides ok / uncertain / lost, or a reason code (app/filter/status.py);
- ``[lifecycle, UNIT: how chosen]``: decides a lifecycle transition (app/tracking/lifecycle.py, the
  recovery's triggers and caps: app/filter/recovery.py, app/tracking/triggers.py);
- ``[estimator, UNIT: how chosen]``: decides inside the estimate (which refined fit the track keeps,
  whether the static prior holds or releases), not the status or the lifecycle;
- ``[work]`` (a budget: evaluations, samples, iterations, draws), ``[method]`` (a numerical method's
  parameter: spreads, strides, windows of an estimator) and ``[measure]`` (what a measurement spans, or a
  calibrated model of one): not decisions.

Decision numbers that are still module constants in the code (files another change owns, or a measure's
definition compiled into the likelihood kernels) are listed in :data:`IN_CODE`; the tests check that each
still exists there.
"""
from __future__ import annotations

import importlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
SECTIONS = ("status", "refine", "recovery")
DECISIONS = ("status", "lifecycle", "estimator")
NOT_DECISIONS = ("work", "method", "measure")
COUNTED = ("status", "lifecycle")          # the "status and lifecycle together"
_TAG = re.compile(r"\[(?P<kind>[a-z]+)(?:, (?P<unit>[^:\]]+): (?P<chosen>[^\]]+))?\]\s*$")
_LINE = re.compile(r"^  (?P<key>[a-z_0-9]+): (?P<value>[^#]+?)\s*(?:#\s?(?P<comment>.*))?$")

# (file, constant, kind, unit, what it decides): decision numbers not (yet) in configs/default.yaml
IN_CODE: tuple[tuple[str, str, str, str, str], ...] = (
)
# (file, constant or field, unit, what it defines): the measures' own levels, compiled into the kernels
MEASURES_IN_CODE: tuple[tuple[str, str, str, str], ...] = (
    ("app/filter/likelihood_ref.py", "INLIER_SIGMAS", "sigma", "an inlier of the status's inlier fraction (3)"),
    ("app/filter/refine.py", "confirm_sigmas", "sigma", "a confirmed measurement of the fitness (3)"),
    ("app/filter/refine.py", "sharp_sigmas", "sigma", "the sharp share that ranks two fits (1)"),
    ("app/filter/refine.py", "behind_sigmas", "sigma", "a measurement behind the model (1)"),
)


@dataclass(frozen=True)
class Number:
    """One numeric key of default.yaml: ``key`` (dotted), its value as written, its kind, and for a
    decision its unit and how it was chosen."""

    key: str
    value: str
    kind: str
    unit: str = ""
    chosen: str = ""


def numbers(path: Path = CONFIG) -> list[Number]:
    """Every numeric key of the sections :data:`SECTIONS` with its bracketed kind (module docstring).
    Raises ValueError for a numeric key without a kind, or with an unknown one."""
    out, section = [], None
    for line in Path(path).read_text().splitlines():
        top = re.match(r"^([a-z_]+):", line)
        if top:
            section = top.group(1)
            continue
        m = _LINE.match(line)
        if section not in SECTIONS or m is None or not _numeric(m.group("value")):
            continue
        key = f"{section}.{m.group('key')}"
        tag = _TAG.search(m.group("comment") or "")
        if tag is None or tag.group("kind") not in DECISIONS + NOT_DECISIONS:
            raise ValueError(f"{path}: {key} has no kind at the end of its comment ([status, UNIT: how chosen], "
                             f"[lifecycle, ...], [estimator, ...], [work], [method] or [measure])")
        kind = tag.group("kind")
        if kind in DECISIONS and not tag.group("unit"):
            raise ValueError(f"{path}: {key} is a decision: write [{kind}, UNIT: how chosen]")
        out.append(Number(key, m.group("value"), kind, tag.group("unit") or "", tag.group("chosen") or ""))
    return out


def _numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _value(n: Number) -> str:
    v = float(n.value)
    if n.unit.startswith("rad"):
        return f"{v:.4g} ({math.degrees(v):.3g} deg)"
    return f"{v:g}"


def _in_code(file: str, name: str) -> float:
    """The module constant's value (it must exist: the table stays true)."""
    module = importlib.import_module(file.removesuffix(".py").replace("/", "."))
    return float(getattr(module, name))


def counts(path: Path = CONFIG) -> dict[str, int]:
    """The number of keys of each kind, the decision numbers still in code, and ``status+lifecycle``."""
    out = {k: 0 for k in DECISIONS + NOT_DECISIONS}
    for n in numbers(path):
        out[n.kind] += 1
    for _, _, kind, _, _ in IN_CODE:
        out[f"{kind} in code"] = out.get(f"{kind} in code", 0) + 1
    out["status+lifecycle"] = sum(out[k] + out.get(f"{k} in code", 0) for k in COUNTED)
    return out


def markdown_table(path: Path = CONFIG) -> str:
    """The README's table of the decision numbers (status and lifecycle, then the estimator's), the
    ones still in code, and the counts."""
    nums = numbers(path)
    rows = ["| key | value | unit | decides | how chosen |", "|---|---|---|---|---|"]
    for kind in DECISIONS:
        rows += [f"| `{n.key}` | {_value(n)} | {n.unit} | {n.kind} | {n.chosen} |" for n in nums if n.kind == kind]
    rows += [f"| `{name}` ({file}) | {_in_code(file, name):g} | {unit} | {kind} | {what} |"
             for file, name, kind, unit, what in IN_CODE]
    c = counts(path)
    not_decisions = ", ".join(f"{c[k]} {k}" for k in NOT_DECISIONS)
    measures = ", ".join(f"`{name}`" for _, name, _, _ in MEASURES_IN_CODE)
    rows += ["", f"Status and lifecycle: **{c['status+lifecycle']}** decision numbers ({c['status']} status and "
             f"{c['lifecycle']} lifecycle keys, {len(IN_CODE)} module constants); the estimator's: {c['estimator']}. "
             f"Not decisions: {not_decisions} keys. The measures' own levels in code: {measures}."]
    return "\n".join(rows)
