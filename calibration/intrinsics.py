"""Camera intrinsics from ChArUco board images, and the camera YAML that trials and sessions use.

Method: for every image, ``cv2.aruco.CharucoDetector.detectBoard`` finds the ChArUco corners and
``CharucoBoard.matchImagePoints`` pairs them with their board coordinates (this replaces
``cv2.aruco.calibrateCameraCharuco``, gone from OpenCV >= 4.7's Python API). Images with fewer than
``MIN_CORNERS`` corners, or corners on one line, are reported and skipped. Then
``cv2.calibrateCameraExtended`` (Zhang's method + Levenberg-Marquardt on the reprojection error,
5-parameter Brown-Conrady distortion k1 k2 p1 p2 k3) gives K, the distortion, and the RMS
reprojection error of each image in pixels.

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

log = logging.getLogger(__name__)

CAMERA_FORMAT = "osteonav-camera/1"
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


def list_images(folder: "str | Path") -> list[Path]:
    """Image files of a folder, sorted by name (non-recursive)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder {folder} does not exist")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def calibrate_intrinsics(images: "dict[str, np.ndarray | None]", board=DEFAULT_BOARD_SPEC,
                         min_corners: int = MIN_CORNERS, min_images: int = 4,
                         fix_k3: bool = False) -> IntrinsicsResult:
    """Calibrate K and distortion from ChArUco images.

    Parameters
    ----------
    images : name -> (H, W) or (H, W, 3) uint8 image (None for an unreadable file, reported).
        All images must have the same size.
    board : board SPEC (``calibration.board``).
    min_images : fewest usable images; fewer raises ValueError.
    fix_k3 : keep k3 = 0 (``cv2.CALIB_FIX_K3``): advisable for ordinary lenses and few views,
        where k3 otherwise absorbs noise.

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
    rms, K, dist, _, _, _, _, per_view = cv2.calibrateCameraExtended(
        obj_points, img_points, (w, h), None, None, flags=cv2.CALIB_FIX_K3 if fix_k3 else 0)
    per_image = [{"image": n, "error_px": float(e), "corners": int(c)}
                 for n, e, c in zip(names, np.ravel(per_view), counts)]
    cam = CameraIntrinsics(np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel(),
                           w, h)
    return IntrinsicsResult(cam, float(rms), spec.to_string(), per_image, skipped)


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
    return {"board": result.board, "rms_px": result.rms_px, "images": result.per_image,
            "skipped": result.skipped}
