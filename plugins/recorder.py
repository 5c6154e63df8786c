"""The recorder: the session's sensor streams written as a trial (RECORDING_FORMAT.md) as they come.

Used by ``osteonav record`` and by a session's ``record: DIR``. Every accepted frame and joint
sample is queued (``on_frame``/``on_joints`` return at once) and a writer thread hands them to
:class:`app.trial.writer.TrialWriter`: the loop never waits for the disk. The queue is bounded twice:
by what its frames weigh (``max_queue_mb``, 256 MB by default: about 200 frames of 640x480 float32
depth, ~7 s at 30 Hz, fewer with infrared and colour images) and by its items (``max_queue``, frames
and joint batches together). If the disk falls that far behind, the oldest frames (for the byte
bound) or items are dropped, counted and reported, never silently lost. The item bound alone let a
writer slower than the camera (a busy host) hold up to 2048 frames, 2.5 GB of depth: the session's
memory grew by 150-350 MB a minute until it was reached.

Crash safety rests on the writer's order of work: ``trial.yaml`` first, each PNG complete before
its ``frames.csv`` row, rows flushed as written, so a kill leaves every frame listed so far
readable. Frame ids that do not increase (a camera restarted its counter) are renumbered after the
last one, and said so.

Image streams: when the camera declares infrared and/or colour (``context['image_streams']``, from
its ``session_defaults()``), the trial is written in format 1.1 with those streams, each frame's
images beside its depth. A frame that lacks a declared image (the camera dropped it) is not written
(format 1.1: every listed frame has one PNG per stream); such frames are counted and reported.

A recording is complete or says it is not. Every frame lost is counted where it was lost
(:attr:`Recorder.dropped`): ``camera`` (a gap in the frame ids handed to the recorder: the camera,
or the session before the recorder, never delivered it; or a frame without a declared image),
``queue`` (dropped because the disk fell behind), ``disk`` (a write failed, e.g. the disk is full:
that frame and every later one). The counts go into trial.yaml (``dropped: {camera, queue, disk}``)
and the report (with ``joint_samples_lost``); when the queue or the disk lost frames or joint
samples, or the writer failed, the trial keeps its ``.recording-in-progress`` marker and the
report's ``complete`` is false (``osteonav record`` then exits non-zero).
"""
from __future__ import annotations

import logging
import threading
from pathlib import Path

from app.errors import megabytes
from app.interfaces import DepthFrame, DropOldestQueue, Estimate, JointSamples, SessionEvent

log = logging.getLogger(__name__)

DEPTH_SCALE_MM = 0.1  # PNG unit: 0.1 mm, up to 6.55 m


class Recorder:
    kind, name = "output", "recorder"

    def __init__(self, dir: str, overwrite: bool = False, max_queue: int = 2048, max_queue_mb: float = 256.0):
        self.dir = Path(dir)
        self.overwrite = bool(overwrite)
        queue_mb = megabytes(max_queue_mb, "output.params.max_queue_mb", 256)
        self.queue = DropOldestQueue(int(max_queue), max_bytes=int(queue_mb * 1e6), nbytes=_item_bytes)
        self.writer = None
        self._thread = None
        self._done = threading.Event()
        self.frames_written = 0
        self.joints_written = 0
        self.renumbered = 0
        self.incomplete = 0
        self._last_id = -1
        self._last_seen_id: int | None = None
        self.frames_in = 0        # handed to the recorder (on_frame)
        self.frames_taken = 0     # taken from the queue by the writer thread
        self.joints_in = 0        # joint samples handed to the recorder
        self.joints_taken = 0
        self.camera_gaps = 0
        self.disk_lost = 0
        self.error: str | None = None

    def open(self, context: dict) -> None:
        from app.errors import ConfigError
        from app.image_streams import ImageStreams
        from app.trial.meta import TrialMeta
        from app.trial.writer import TrialWriter

        mesh_path = context.get("mesh_path")
        if mesh_path is None:
            raise ConfigError("bone.mesh", "missing: a recorded trial names its bone mesh (RECORDING_FORMAT.md)")
        initial_pose = context.get("initial_pose")
        meta = TrialMeta(camera=context["camera"], depth_scale=DEPTH_SCALE_MM, robot=dict(context["robot"]),
                         dh=context["dh"], T_flange_camera=context["T_flange_camera"], mesh=Path(mesh_path).name,
                         initial_pose=initial_pose, point_prior=None,
                         extra={"recorded_by": "osteonav record", "session": str(context.get("session_file"))},
                         streams=context.get("image_streams") or ImageStreams())
        self.writer = TrialWriter(self.dir, meta, mesh_source=mesh_path, overwrite=self.overwrite)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def on_frame(self, frame: DepthFrame) -> None:
        last, frame_id = self._last_seen_id, int(frame.frame_id)
        if last is not None and frame_id > last + 1:
            self.camera_gaps += frame_id - last - 1
        self._last_seen_id = frame_id if last is None else max(last, frame_id)
        self.frames_in += 1
        self.queue.put(("frame", frame))

    def on_joints(self, samples: JointSamples) -> None:
        self.joints_in += len(samples.stamps)
        self.queue.put(("joints", samples))

    def on_estimate(self, est: Estimate) -> None:
        pass

    def on_event(self, event: SessionEvent) -> None:
        pass

    def _write(self, item) -> None:
        what, data = item
        if what == "frame":
            streams = self.writer.meta.streams
            if (streams.infrared is not None and data.infrared is None) or (streams.color is not None and data.color is None):
                self.incomplete += 1
                return
            frame_id = data.frame_id
            if frame_id <= self._last_id:
                frame_id = self._last_id + 1
                self.renumbered += 1
            self.writer.write_frame(frame_id, data.stamp, data.depth_m, infrared=data.infrared, color=data.color)
            self._last_id = frame_id
            self.frames_written += 1
        else:
            self.writer.write_joints(data.stamps, data.q)
            self.joints_written += len(data.stamps)

    @property
    def dropped(self) -> dict:
        """Frames lost, by where: camera, queue, disk (module docstring)."""
        return {"camera": self.camera_gaps + self.incomplete, "queue": self.frames_in - self.frames_taken,
                "disk": self.disk_lost}

    def _run(self) -> None:
        """Write what the queue holds until closed; after a failed write, keep taking frames and count them lost."""
        while not self._done.is_set() or len(self.queue):
            item = self.queue.get(timeout=0.1)
            if item is None:
                continue
            if item[0] == "frame":
                self.frames_taken += 1
            else:
                self.joints_taken += len(item[1].stamps)
            if self.error is not None:
                self.disk_lost += item[0] == "frame"
                continue
            try:
                self._write(item)
            except Exception as exc:  # disk full, permissions: stop writing, keep the session going
                self.error = _failure(exc)
                self.disk_lost += item[0] == "frame"
                log.error("recorder: %s; the frames from now on are not recorded", self.error)

    @property
    def joint_samples_lost(self) -> int:
        """Joint samples handed to the recorder and not written (dropped in the queue, or after a failed write)."""
        return self.joints_in - self.joints_written

    @property
    def complete(self) -> bool:
        """Every frame and joint sample handed to the recorder written (camera gaps aside), no write failed."""
        dropped = self.dropped
        return self.error is None and not dropped["queue"] and not dropped["disk"] and not self.joint_samples_lost

    def close(self) -> dict:
        self._done.set()
        if self._thread is not None:
            self._thread.join()
        dropped, complete = self.dropped, self.complete
        if self.writer is not None:
            try:
                self.writer.note("dropped", dropped)
            except OSError as exc:
                log.error("recorder: cannot record the drop counts in trial.yaml (%s)", _failure(exc))
            self.writer.close(complete=complete)
        if any(dropped.values()):
            log.warning("recorder: frames dropped: %d by the camera (gaps), %d in the queue (the disk fell behind), "
                        "%d not written (%s)", dropped["camera"], dropped["queue"], dropped["disk"],
                        self.error or "no write failed")
        if self.queue.dropped:
            log.warning("recorder: %d items dropped (the disk fell behind)", self.queue.dropped)
        if self.renumbered:
            log.warning("recorder: %d frames renumbered (the camera's counter went back)", self.renumbered)
        if self.incomplete:
            log.warning("recorder: %d frames without a declared infrared/colour image not written", self.incomplete)
        return {"dir": str(self.dir), "frames": self.frames_written, "joint_samples": self.joints_written,
                "dropped": dropped, "joint_samples_lost": self.joint_samples_lost, "complete": complete, "renumbered": self.renumbered, "incomplete": self.incomplete,
                "error": self.error}


def _item_bytes(item) -> int:
    """What a queued item weighs against ``max_queue_mb``: a frame's depth and images; a joint batch 0
    (small, bounded by ``max_queue``)."""
    what, data = item
    if what != "frame":
        return 0
    return sum(int(getattr(a, "nbytes", 0)) for a in (data.depth_m, data.infrared, data.color) if a is not None)


def _failure(exc: Exception) -> str:
    """A one-line reason for a failed write (a full disk said so)."""
    import errno

    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return f"the disk is full ({exc.filename or exc})"
    return f"{type(exc).__name__}: {exc}"
