"""Is the truth the best explanation of a frame? The likelihood and the refinement at the ground truth
against the best poses a wide search finds elsewhere (``osteonav diagnose-likelihood``).

Import as ``from app.bench import ambiguity``. Issue 12 / DESIGN.md "Local refinement": on a CT crest
under residual tissue the frame's likelihood was higher with the bone laid along the tissue than at
the truth. Per frame this module

1. scores the ground truth with the tracker's likelihood (the GL backend at the filter's resolution,
   the configured model) and with the refinement's fit (app/filter/refine.py, not iterated: the
   share of the expected visible surface confirmed within 3 σ and within 1 σ);
2. searches widely: ``candidates`` poses drawn around the truth (uniform direction, translation up
   to ``search_mm``, rotation up to ``search_deg``), scored in batches by the same likelihood;
3. keeps the ``top`` best that lie more than 5 mm or 5 deg from the truth, refines each (the
   tracker's refinement, iterated) and reports the best competitor by log-likelihood and by fit.

A frame is ambiguous for the filter when a competitor's log-likelihood reaches the truth's, and
for the refinement when a refined competitor's fit comes within the status's margin of the truth's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.filter.observation import finite_log_likelihood
from app.geometry import se3

APART_M = 0.005
APART_RAD = np.radians(5.0)


@dataclass
class FrameDiagnosis:
    """One frame: the truth's log-likelihood and fits, the best competitor's (by likelihood) pose
    error (mm, deg), log-likelihood and refined fits, and the best refined competitor's fit."""

    frame: int
    ll_truth: float
    fit_truth: float
    sharp_truth: float
    ll_best: float
    best_mm: float
    best_deg: float
    fit_best_refined: float
    sharp_best_refined: float
    refined_mm: float
    refined_deg: float


def random_poses(T_center: np.ndarray, n: int, max_m: float, max_rad: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) poses T_center · exp(ω, t), |t| ~ U(0, max_m), |ω| ~ U(0, max_rad), uniform directions,
    the perturbation about the bone's origin expressed in the bone frame."""
    def directions(k):
        d = rng.normal(size=(k, 3))
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    t = directions(n) * rng.uniform(0, max_m, (n, 1))
    w = directions(n) * rng.uniform(0, max_rad, (n, 1))
    return np.stack([T_center @ se3.from_rotvec_trans(w[i], t[i]) for i in range(n)])


def score(backend, T_camera_bone: np.ndarray, depth_small: np.ndarray, batch: int) -> np.ndarray:
    """log p(z | x) of many poses through a backend that takes at most ``batch`` per call."""
    out = [np.asarray(backend.log_likelihood(T_camera_bone[i:i + batch], depth_small), float)
           for i in range(0, len(T_camera_bone), batch)]
    return finite_log_likelihood(np.concatenate(out))[0]   # the one non-finite policy: NaN / +inf -> -inf


def diagnose_frame(index, backend, refiner, depth_full, depth_small, T_camera_bone_true, rng, batch,
                   candidates=2000, search_mm=40.0, search_deg=40.0, top=4) -> tuple[FrameDiagnosis, np.ndarray]:
    """The comparison of the module docstring for one frame; also returns the best competitor's pose."""
    ll_truth = float(score(backend, T_camera_bone_true[None], depth_small, batch)[0])
    iterations = refiner.params.iterations
    refiner.params.iterations = 0
    at_truth = refiner.refine(depth_full, T_camera_bone_true)
    refiner.params.iterations = iterations
    poses = random_poses(T_camera_bone_true, candidates, search_mm / 1e3, np.radians(search_deg), rng)
    ll = score(backend, poses, depth_small, batch)
    dist = se3.translation_distance(poses, T_camera_bone_true[None])
    angle = se3.rotation_angle(poses, T_camera_bone_true[None])
    apart = (dist > APART_M) | (angle > APART_RAD)
    order = [i for i in np.argsort(-ll) if apart[i]][:top]
    best = order[0]
    refined = [refiner.refine(depth_full, poses[i]) for i in order]
    refined_apart = [r for r in refined if se3.translation_distance(r.T_camera_bone, T_camera_bone_true) > APART_M
                     or se3.rotation_angle(r.T_camera_bone, T_camera_bone_true) > APART_RAD]
    fit_r = max(refined_apart, key=lambda r: r.sharp) if refined_apart else None
    diag = FrameDiagnosis(
        frame=index, ll_truth=ll_truth, fit_truth=at_truth.fitness, sharp_truth=at_truth.sharp,
        ll_best=float(ll[best]), best_mm=1e3 * float(dist[best]), best_deg=float(np.degrees(angle[best])),
        fit_best_refined=fit_r.fitness if fit_r else float("nan"),
        sharp_best_refined=fit_r.sharp if fit_r else float("nan"),
        refined_mm=1e3 * float(se3.translation_distance(fit_r.T_camera_bone, T_camera_bone_true)) if fit_r else float("nan"),
        refined_deg=float(np.degrees(se3.rotation_angle(fit_r.T_camera_bone, T_camera_bone_true))) if fit_r else float("nan"))
    return diag, poses[best]


def table(rows: list[FrameDiagnosis]) -> str:
    """A markdown table of the frames."""
    head = ("| frame | LL truth | LL best other | other mm / deg | fit truth (3σ / 1σ) | refined other fit (3σ / 1σ) "
            "| refined other mm / deg |\n|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        lines.append(f"| {r.frame} | {r.ll_truth:.1f} | {r.ll_best:.1f} | {r.best_mm:.1f} / {r.best_deg:.1f} | "
                     f"{r.fit_truth:.2f} / {r.sharp_truth:.2f} | {r.fit_best_refined:.2f} / {r.sharp_best_refined:.2f} | "
                     f"{r.refined_mm:.1f} / {r.refined_deg:.1f} |")
    return "\n".join(lines)
