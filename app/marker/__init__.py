"""Publication C's augmented-marker navigation: an ArUco marker and an IMU on the acetabular fragment.

One concept per module (import each one by name; nothing is re-exported here):

- :mod:`app.marker.aruco`            ArUco detection (region of interest first, whole image as fallback), IPPE pose
- :mod:`app.marker.imu`              IMU samples: the UDP protocol, receiver, validator, CSV files
- :mod:`app.marker.handeye_rotation` IMU-to-marker rotation, AX = XB in closed form (Park & Martin)
- :mod:`app.marker.kalman`           error-state Kalman filter on the marker orientation (IMU predicts, marker corrects)
- :mod:`app.marker.fusion`           the tracker: IMU samples and camera images in stamp order -> orientations
- :mod:`app.marker.pelvic_plane`     anterior pelvic plane, radiographic inclination and anteversion
- :mod:`app.marker.simulator`        a moving fragment: rendered marker images and a drifting IMU
- :mod:`app.marker.bench`            marker-only / IMU-only / fused errors and rates (``osteonav bench-marker``)

Frames: C camera (OpenCV), M marker (ArUco: origin at the centre, x right, y up, z out of the
marker's face), S IMU sensor, W the IMU's own world (gravity-aligned, yaw arbitrary and drifting:
no magnetometer), P anterior pelvic plane. ``R_a_b`` is the rotation of frame b in frame a.
"""
