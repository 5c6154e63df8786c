"""Success against budget: how many starts each method has solved within B likelihood evaluations.

Import as ``from app.bench import budget``; used by ``osteonav bench-init`` (issue 33, item 4: "a plot
of success against budget"). One run per start and method gives, for each, whether it succeeded and
the likelihood evaluations it had spent when it did (``evaluations_to_success``, None when it did
not):

- MH and multiple-try Metropolis (app/bench/samplers.py): the evaluation count from which their
  best pose so far is a success to the end of the run; a run with a smaller budget is a prefix of
  this one (the same generator, the same chains), so the count is exact for every budget below the
  one run;
- the SMC, the verified SMC and the detector give one answer at the end: their count is the whole
  run's, and the curve reads "solved at a budget of at least what it spent" (a smaller budget is a
  different run, not measured);
- ``bench-init`` without ``--samplers``: the detector in the replay, solved when the frame it found
  the bone on is within 1 mm, at the evaluations of all its attempts up to then.

The curve of a method is a step function of the budget B: ``successes(B) = #{starts : solved with
evaluations_to_success <= B}``, non-decreasing by construction, evaluated at every budget where some
method steps (and at the largest budget spent). :func:`curve` computes it, :func:`plot` draws it as
a PNG (matplotlib, Agg: no display).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def curve(rows: list[dict], method_key: str = "sampler") -> dict:
    """Success against budget over ``rows`` (one per start and method).

    Parameters
    ----------
    rows : dicts with ``method_key`` (the method's name), ``evaluations_to_success`` (int, or None when
        not solved) and ``evaluations`` (int, spent)
    method_key : the key naming the method

    Returns
    -------
    dict: ``budgets`` (ascending ints, likelihood evaluations), ``starts`` (per method, the number of
    starts), ``successes`` (per method, the count solved within each budget, non-decreasing).
    """
    methods = list(dict.fromkeys(r[method_key] for r in rows))
    solved = {m: [int(r["evaluations_to_success"]) for r in rows
                  if r[method_key] == m and r["evaluations_to_success"] is not None] for m in methods}
    spent = [int(r["evaluations"]) for r in rows if r.get("evaluations") is not None]
    budgets = sorted({0, *(e for s in solved.values() for e in s), *([max(spent)] if spent else [])})
    successes = {m: [int(np.sum(np.asarray(solved[m], dtype=np.int64) <= b)) for b in budgets] for m in methods}
    starts = {m: sum(1 for r in rows if r[method_key] == m) for m in methods}
    return {"budgets": budgets, "starts": starts, "successes": successes}


def plot(result: dict, path: Path, title: str) -> Path:
    """Draw :func:`curve`'s ``result`` (the share of starts solved against the budget, one step line per
    method, the budget on a log axis) as a PNG at ``path``; returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    budgets = np.asarray(result["budgets"], float)
    fig, ax = plt.subplots(figsize=(7.0, 4.2), dpi=110)
    try:
        styles = ("-", "--", "-.", ":")
        for k, (method, counts) in enumerate(result["successes"].items()):
            share = np.asarray(counts, float) / max(result["starts"][method], 1)
            x = np.maximum(budgets, 1.0)            # the log axis starts at one evaluation
            # lines that coincide (several methods at 0) stay visible: a style and a width each
            ax.step(x, share, where="post", linestyle=styles[k % len(styles)], linewidth=2.6 - 0.4 * (k % 4),
                    label=f"{method} ({counts[-1]}/{result['starts'][method]})")
        ax.set_xscale("log")
        ax.set_xlabel("likelihood evaluations (budget)")
        ax.set_ylabel("share of starts solved")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title(title, fontsize=9)
        ax.legend(loc="upper left", fontsize=8)
        fig.tight_layout()
        fig.savefig(path, format="png")
    finally:
        plt.close(fig)
    return Path(path)
