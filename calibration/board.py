"""ChArUco calibration boards: the spec string, the OpenCV board, detection and board pose.

Board SPEC
----------
A board is named by a short string ``charuco:SXxSY:SQUARE:MARKER:DICT``, e.g. the default

    charuco:7x5:0.04:0.03:DICT_5X5_100

= a ChArUco board of 7 x 5 chessboard squares (x by y), square side 0.04 m, ArUco marker side
0.03 m, markers from OpenCV's predefined dictionary ``cv2.aruco.DICT_5X5_100``. The same as a YAML
mapping (inline, or in a ``.yaml`` file whose path is given instead of the string)::

    {type: charuco, squares: [7, 5], square_length: 0.04, marker_length: 0.03,
     dictionary: DICT_5X5_100}

The board frame is OpenCV's: origin at the outer corner of the first square (top left of the
generated image), x along the SX squares, y along the SY squares, z into the board (x right, y down
in the image, so z points away from a camera that sees the printed side). The inner chessboard
corners (``(SX-1)(SY-1)`` of them, ids 0.. in row-major order) lie at ``(i, j) * SQUARE``.

The generated image (``board_image``) maps board point (x, y) to pixel
``(x, y) * px_per_m - 0.5`` (pixel centres at integers): the simulator relies on this.

OpenCV API used (OpenCV >= 4.7, including 5.0): ``cv2.aruco.CharucoBoard``,
``cv2.aruco.CharucoDetector.detectBoard``, ``CharucoBoard.matchImagePoints``, ``cv2.solvePnP``.
The older ``cv2.aruco.calibrateCameraCharuco`` / ``estimatePoseCharucoBoard`` do not exist there.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

DEFAULT_BOARD_SPEC = "charuco:7x5:0.04:0.03:DICT_5X5_100"
MIN_CORNERS = 6
"""Fewest ChArUco corners for a usable detection (a homography needs 4; PnP is fragile below 6)."""


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board. Lengths in metres."""

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float
    dictionary: str

    def to_string(self) -> str:
        return (f"charuco:{self.squares_x}x{self.squares_y}:{self.square_length:g}:"
                f"{self.marker_length:g}:{self.dictionary}")

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the board in metres."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length


def _spec_error(spec, why: str) -> ValueError:
    return ValueError(
        f"board spec {spec!r}: {why}; expected 'charuco:SXxSY:SQUARE_M:MARKER_M:DICT' such as "
        f"{DEFAULT_BOARD_SPEC!r}, a YAML mapping with keys type, squares, square_length, "
        f"marker_length, dictionary, or the path of a YAML file holding one")


def parse_board_spec(spec: "str | dict | BoardSpec | Path") -> BoardSpec:
    """Parse a board SPEC (see the module docstring); raises ValueError naming what is wrong."""
    if isinstance(spec, BoardSpec):
        return spec
    if isinstance(spec, Path) or (isinstance(spec, str) and spec.endswith((".yaml", ".yml"))):
        import yaml

        data = yaml.safe_load(Path(spec).read_text())
        if isinstance(data, dict) and "board" in data:
            data = data["board"]
        return parse_board_spec(data)
    if isinstance(spec, str) and spec.strip().startswith("{"):
        import yaml

        return parse_board_spec(yaml.safe_load(spec))
    if isinstance(spec, dict):
        try:
            kind = spec.get("type", "charuco")
            sx, sy = spec["squares"]
            out = BoardSpec(int(sx), int(sy), float(spec["square_length"]),
                            float(spec["marker_length"]), str(spec["dictionary"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise _spec_error(spec, f"bad or missing key ({exc})") from None
    elif isinstance(spec, str):
        parts = spec.strip().split(":")
        if len(parts) != 5:
            raise _spec_error(spec, f"{len(parts)} ':'-separated fields, expected 5")
        kind = parts[0]
        try:
            sx, sy = (int(v) for v in parts[1].lower().split("x"))
            out = BoardSpec(sx, sy, float(parts[2]), float(parts[3]), parts[4])
        except ValueError as exc:
            raise _spec_error(spec, str(exc)) from None
    else:
        raise _spec_error(spec, f"unsupported type {type(spec).__name__}")
    if kind != "charuco":
        raise _spec_error(spec, f"board type {kind!r} is not supported (only 'charuco')")
    if out.squares_x < 3 or out.squares_y < 3:
        raise _spec_error(spec, "needs at least 3 squares each way")
    if not 0 < out.marker_length < out.square_length:
        raise _spec_error(spec, "needs 0 < marker length < square length (metres)")
    import cv2

    if not out.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, out.dictionary):
        raise _spec_error(spec, f"unknown ArUco dictionary {out.dictionary!r} (e.g. DICT_5X5_100)")
    return out


def make_board(spec: "BoardSpec | str"):
    """The ``cv2.aruco.CharucoBoard`` of a spec."""
    import cv2

    spec = parse_board_spec(spec)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_length,
                                   spec.marker_length, dictionary)
    n_markers = (spec.squares_x * spec.squares_y) // 2
    if n_markers > dictionary.bytesList.shape[0]:
        raise _spec_error(spec.to_string(), f"{n_markers} markers do not fit {spec.dictionary}")
    return board


def board_image(spec: "BoardSpec | str", px_per_square: int = 100) -> tuple[np.ndarray, float]:
    """OpenCV's rendering of the board, no margin.

    Returns
    -------
    image : (SY * px_per_square, SX * px_per_square) uint8, black on white.
    px_per_m : float, pixels per metre: board point (x, y) is at pixel (x, y) * px_per_m - 0.5.
    """
    spec = parse_board_spec(spec)
    board = make_board(spec)
    size = (spec.squares_x * px_per_square, spec.squares_y * px_per_square)
    image = board.generateImage(size, marginSize=0, borderBits=1)
    return image, px_per_square / spec.square_length


@dataclass
class Detection:
    """ChArUco corners found in one image.

    ids : (M,) int, corner ids; corners_px : (M, 2) float64, pixel positions (u, v);
    points_board : (M, 3) float64, the same corners in the board frame, metres.
    """

    ids: np.ndarray
    corners_px: np.ndarray
    points_board: np.ndarray


class BoardDetector:
    """Detects a ChArUco board in grey or BGR images (``cv2.aruco.CharucoDetector``)."""

    def __init__(self, spec: "BoardSpec | str" = DEFAULT_BOARD_SPEC, min_corners: int = MIN_CORNERS):
        import cv2

        self.spec = parse_board_spec(spec)
        self.board = make_board(self.spec)
        self.min_corners = int(min_corners)
        self._detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray) -> tuple[Detection | None, str]:
        """Detect the board; returns (detection, "") or (None, reason it is unusable)."""
        import cv2

        if image is None or image.size == 0:
            return None, "empty image"
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if grey.dtype != np.uint8:
            return None, f"expected an 8-bit image, got {grey.dtype}"
        corners, ids, _, marker_ids = self._detector.detectBoard(grey)
        n = 0 if ids is None else len(ids)
        if n < self.min_corners:
            markers = 0 if marker_ids is None else len(marker_ids)
            return None, f"{n} ChArUco corners found ({markers} markers), need {self.min_corners}"
        obj, img = self.board.matchImagePoints(corners, ids)
        pts = obj.reshape(-1, 3).astype(np.float64)
        if self._collinear(pts):
            return None, f"the {n} corners found lie on one line"
        return Detection(ids.ravel().astype(int), img.reshape(-1, 2).astype(np.float64), pts), ""

    @staticmethod
    def _collinear(points_board: np.ndarray) -> bool:
        centred = points_board[:, :2] - points_board[:, :2].mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        return s[1] < 1e-6 * max(s[0], 1e-12) or s[1] < 1e-9


def board_pose(detection: Detection, K: np.ndarray, dist: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Board pose in the camera optical frame from one detection (PnP, then LM refinement).

    Parameters
    ----------
    detection : the board's corners in the image.
    K : (3, 3) float64 intrinsics, pixels. dist : OpenCV distortion coefficients or None.

    Returns
    -------
    T_camera_board : (4, 4) float64, metres.
    errors_px : (M,) float64, reprojection error of each corner, pixels.
    """
    import cv2

    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
    obj = detection.points_board.reshape(-1, 1, 3)
    img = detection.corners_px.reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("solvePnP failed on the board's corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    errors = np.linalg.norm(proj.reshape(-1, 2) - detection.corners_px, axis=1)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, errors
