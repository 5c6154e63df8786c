"""Calibration tools: camera intrinsics (ChArUco) and eye-in-hand hand-eye (AX = XB).

Modules (OpenCV and ``app.geometry`` only; no GL):
- ``calibration.board``: the board SPEC string (``DEFAULT_BOARD_SPEC``), OpenCV's ChArUco board,
  detection (``BoardDetector``) and the board pose in the camera (``board_pose``).
- ``calibration.intrinsics``: K and distortion from board images; the camera YAML.
- ``calibration.captures``: the capture-folder format, reader/writer, live collection protocol.
- ``calibration.solvers``: AX = XB and AX = ZB solvers by name (OpenCV's calibrateHandEye /
  calibrateRobotWorldHandEye).
- ``calibration.handeye``: the pipeline from a capture folder to T_flange_camera, residuals,
  conditioning warnings and the hand-eye YAML.
- ``calibration.simulator``: rendered ChArUco views from a simulated UR5e with a known hand-eye.
- ``calibration.rerun_log``: captures, camera frusta and the board to an .rrd file.

The command line is ``osteonav calibrate {simulate,intrinsics,hand-eye,capture}``
(``app/commands/calibrate.py``).
"""
