"""Camera intrinsics from ChArUco board images, and the camera YAML that trials and sessions use.

Method: for every image, ``cv2.aruco.CharucoDetector.detectBoard`` finds the ChArUco corners and
``CharucoBoard.matchImagePoints`` pairs them with their board coordinates (this replaces
``cv2.aruco.calibrateCameraCharuco``, gone from OpenCV >= 4.7's Python API). Images with fewer than
``MIN_CORNERS`` corners, or corners on one line, are reported and skipped. Then
``cv2.calibrateCameraExtended`` (Zhang's method + Levenberg-Marquardt on the reprojection error,
5-parameter Brown-Conrady distortion k1 k2 p1 p2 k3) gives K, the distortion, and the RMS
reprojection error of each image in pixels.

k3 (the r^6 term) is only kept when the images constrain it. Both models are fitted, with k3 free
and with k3 = 0; k3 is kept when it lowers the RMS reprojection error by at least
``K3_MIN_RMS_GAIN`` (relative): (rms_fixed - rms_free) / rms_fixed >= 0.05. Otherwise it is fixed
at 0 and, when the two models disagree by more than ``K3_WARN_PX`` at the image corners (k3
extrapolating beyond the board's coverage), a warning gives both RMS and that disagreement. On the
documented simulated flow (calibrate simulate --noise, 20 captures) the free k3 lowered the RMS by
0.1 % yet put the image corners 35 px off the true model; with k3 fixed they are 3 px off.

Camera YAML (written by ``write_camera_yaml``, read by ``read_camera_yaml``)::

    format: osteonav-camera/1
    camera:                      # the same block as trial.yaml's camera, plus dist
      width: 640
      height: 480
      K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]      # pixels
      dist: [k1, k2, p1, p2, k3]                    # OpenCV's order
    calibration:                 # how it was obtained (informative)
      board: charuco:7x5:0.04:0.03:DICT_5X5_100
      rms_px: 0.12
      images: [{image: a.png, error_px: 0.11, corners: 24}, ...]
      skipped: [{image: b.png, reason: ...}]
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.board import DEFAULT_BOARD_SPEC, MIN_CORNERS, BoardDetector, parse_board_spec
from app.outputs import wrote

log = logging.getLogger(__name__)

CAMERA_FORMAT = "osteonav-camera/1"
K3_MIN_RMS_GAIN = 0.05
"""Least relative RMS reduction that justifies a free k3 (a lens with real r^6 distortion gives far more)."""
K3_WARN_PX = 1.0
"""Disagreement at the image corners (pixels) between the free-k3 and k3 = 0 models worth a warning."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass
class CameraIntrinsics:
    """Pinhole intrinsics with OpenCV distortion.

    K : (3, 3) float64, pixels. dist : (5,) float64 (k1, k2, p1, p2, k3). width, height : pixels.
    """

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int

    def to_dict(self) -> dict:
        return {"width": int(self.width), "height": int(self.height),
                "K": [[float(v) for v in row] for row in self.K],
                "dist": [float(v) for v in np.ravel(self.dist)]}

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "CameraIntrinsics":
        from app.errors import ConfigError

        try:
            K = np.asarray(d["K"], dtype=np.float64)
            width, height = int(d["width"]), int(d["height"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError("camera", f"needs width, height and K ({exc})", source) from None
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ConfigError("camera.K", f"expected a finite 3x3 matrix, got shape {K.shape}", source)
        dist = np.asarray(d.get("dist", [0.0] * 5), dtype=np.float64).ravel()
        if dist.size not in (4, 5, 8, 12, 14) or not np.isfinite(dist).all():
            raise ConfigError("camera.dist", f"expected 4, 5, 8, 12 or 14 finite OpenCV coefficients, "
                              f"got {dist.size}", source)
        return cls(K, dist, width, height)


@dataclass
class IntrinsicsResult:
    camera: CameraIntrinsics
    rms_px: float
    board: str
    per_image: list[dict] = field(default_factory=list)   # {image, error_px, corners}
    skipped: list[dict] = field(default_factory=list)     # {image, reason}
    k3: str = "free"                                       # free | fixed (asked) | fixed (not constrained)
    warnings: list[str] = field(default_factory=list)


def list_images(folder: "str | Path") -> list[Path]:
    """Image files of a folder, sorted by name (non-recursive)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} does not exist")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def calibrate_intrinsics(images: "dict[str, np.ndarray | None]", board=DEFAULT_BOARD_SPEC,
                         min_corners: int = MIN_CORNERS, min_images: int = 4,
                         fix_k3: bool | None = None) -> IntrinsicsResult:
    """Calibrate K and distortion from ChArUco images.

    Parameters
    ----------
    images : name -> (H, W) or (H, W, 3) uint8 image (None for an unreadable file, reported).
        All images must have the same size.
    board : board SPEC (``calibration.board``).
    min_images : fewest usable images; fewer raises ValueError.
    fix_k3 : True keeps k3 = 0 (``cv2.CALIB_FIX_K3``), False frees it, None (default) decides from
        the images (module docstring: free only when it lowers the RMS by ``K3_MIN_RMS_GAIN``).

    Returns
    -------
    IntrinsicsResult with per-image RMS reprojection errors (pixels) and skipped images.
    """
    import cv2

    spec = parse_board_spec(board)
    detector = BoardDetector(spec, min_corners=min_corners)
    obj_points, img_points, names, skipped, counts = [], [], [], [], []
    size = None
    for name, image in images.items():
        if image is None:
            skipped.append({"image": name, "reason": "unreadable image file"})
            continue
        hw = image.shape[:2]
        if size is None:
            size = hw
        elif hw != size:
            skipped.append({"image": name, "reason": f"size {hw[1]}x{hw[0]} differs from the first "
                                                    f"image's {size[1]}x{size[0]}"})
            continue
        det, why = detector.detect(image)
        if det is None:
            skipped.append({"image": name, "reason": why})
            continue
        obj_points.append(det.points_board.astype(np.float32).reshape(-1, 1, 3))
        img_points.append(det.corners_px.astype(np.float32).reshape(-1, 1, 2))
        names.append(name)
        counts.append(len(det.ids))
    for s in skipped:
        log.warning("skipping %s: %s", s["image"], s["reason"])
    if len(names) < min_images:
        raise ValueError(f"only {len(names)} of {len(images)} images show a usable board "
                         f"({spec.to_string()}); intrinsics need at least {min_images}")
    h, w = size
    fits = {k3: cv2.calibrateCameraExtended(obj_points, img_points, (w, h), None, None,
                                            flags=cv2.CALIB_FIX_K3 if k3 == "fixed" else 0)
            for k3 in (("fixed", "free") if fix_k3 is None else ("fixed",) if fix_k3 else ("free",))}
    k3, warnings = _choose_k3(fits, (w, h)) if fix_k3 is None else (next(iter(fits)), [])
    rms, K, dist, _, _, _, _, per_view = fits["fixed" if k3.startswith("fixed") else "free"]
    per_image = [{"image": n, "error_px": float(e), "corners": int(c)}
                 for n, e, c in zip(names, np.ravel(per_view), counts)]
    cam = CameraIntrinsics(np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel(),
                           w, h)
    return IntrinsicsResult(cam, float(rms), spec.to_string(), per_image, skipped, k3, warnings)


def _choose_k3(fits: dict, size: tuple[int, int]) -> tuple[str, list[str]]:
    """'free' or 'fixed (not constrained)' from both fits (module docstring), and the warnings."""
    import cv2

    rms_fixed, rms_free = float(fits["fixed"][0]), float(fits["free"][0])
    gain = (rms_fixed - rms_free) / rms_fixed if rms_fixed > 0 else 0.0
    if gain >= K3_MIN_RMS_GAIN:
        return "free", []
    w, h = size
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64).reshape(-1, 1, 2)
    K_fix, d_fix, K_free, d_free = fits["fixed"][1], fits["fixed"][2], fits["free"][1], fits["free"][2]
    rays = cv2.undistortPoints(corners, K_fix, d_fix).reshape(-1, 2)
    moved, _ = cv2.projectPoints(np.column_stack([rays, np.ones(len(rays))]), np.zeros(3), np.zeros(3), K_free, d_free)
    apart = float(np.linalg.norm(moved.reshape(-1, 2) - corners.reshape(-1, 2), axis=1).max())
    if apart <= K3_WARN_PX:
        return "fixed (not constrained)", []
    return "fixed (not constrained)", [
        f"k3 fixed at 0: the images do not constrain it (a free k3 lowers the RMS only from {rms_fixed:.4f} to "
        f"{rms_free:.4f} px but moves the image corners by {apart:.1f} px); pass --free-k3 to keep it anyway, or add "
        f"views with the board near the image corners"]


def calibrate_intrinsics_folder(folder: "str | Path", board=DEFAULT_BOARD_SPEC, **kwargs) -> IntrinsicsResult:
    """``calibrate_intrinsics`` on every image file of a folder (see ``list_images``)."""
    import cv2

    paths = list_images(folder)
    if not paths:
        raise FileNotFoundError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    images = {p.name: cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths}
    return calibrate_intrinsics(images, board, **kwargs)


def write_camera_yaml(path: "str | Path", camera: CameraIntrinsics, info: dict | None = None) -> None:
    """Write the camera YAML (module docstring); ``info`` becomes the ``calibration`` block."""
    import yaml

    data = {"format": CAMERA_FORMAT, "camera": camera.to_dict()}
    if info:
        data["calibration"] = info
    wrote(path)
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def read_camera_yaml(path: "str | Path") -> CameraIntrinsics:
    """Read a camera YAML (or any YAML with a trial-style ``camera`` block, e.g. trial.yaml)."""
    import yaml

    from app.errors import ConfigError

    data = yaml.safe_load(Path(path).read_text())
    if not isinstance(data, dict) or not isinstance(data.get("camera"), dict):
        raise ConfigError("camera", "expected a 'camera' block with width, height, K", str(path))
    return CameraIntrinsics.from_dict(data["camera"], str(path))


def result_info(result: IntrinsicsResult) -> dict:
    """The ``calibration`` block of the camera YAML for a result."""
    return {"board": result.board, "rms_px": result.rms_px, "k3": result.k3, "images": result.per_image,
            "skipped": result.skipped}
