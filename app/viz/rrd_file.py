"""An ``.rrd`` file whose writes Python makes, so that a failed write is an error, not a hang.

rerun's file sink (``RecordingStream.save``) hangs in ``flush`` when a write fails: a full disk was
seen to hang ``osteonav view --save`` for good. Here rerun saves into a named pipe (a FIFO in a
temporary folder) and a background thread copies the pipe into the file. The file is byte for byte
what ``save`` writes. A failed write (a full disk) is kept, the rest of the pipe is read and dropped
(rerun never blocks), and :meth:`RrdFile.close` raises it as one :class:`app.outputs.OutputError`
naming the file and the reason.

Usage::

    rec = rr.RecordingStream("osteonav")
    rrd = RrdFile(rec, "out/log.rrd")     # the file is listed as an output (app/outputs.py), then created
    rec.log(...)
    rrd.close()                           # OutputError when a write failed
"""
from __future__ import annotations

import errno
import os
import shutil
import tempfile
import threading
from pathlib import Path

from app.outputs import OutputError, wrote

CHUNK = 1 << 16


class RrdFile:
    """``rec``'s data written to ``path`` (see the module docstring)."""

    def __init__(self, rec, path: "str | Path", blueprint=None):
        self.path = Path(path)
        self.error: OSError | None = None
        self.rec = self._rec = rec
        wrote(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._tmp = tempfile.mkdtemp(prefix="osteonav-rrd-")
        self._fifo = os.path.join(self._tmp, "pipe.rrd")
        os.mkfifo(self._fifo)
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._copy, name="rrd-file", daemon=True)
        self._thread.start()
        rec.save(self._fifo, default_blueprint=blueprint)

    def _copy(self) -> None:
        with open(self._fifo, "rb") as pipe:
            self._opened.set()
            while chunk := pipe.read(CHUNK):
                if self.error is not None:
                    continue
                try:
                    self._file.write(chunk)
                except OSError as exc:
                    self.error = exc

    def close(self) -> None:
        """Flush and disconnect the recording, copy what is left; raises OutputError when a write failed."""
        if self._fifo is None:
            return
        self._rec.flush()
        self._rec.disconnect()             # rerun closes its end of the pipe: the copy reads to its end
        if not self._opened.is_set():      # rerun never opened the pipe: end the copy's wait
            try:
                os.close(os.open(self._fifo, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:
                pass
        self._thread.join()
        self._fifo = None
        shutil.rmtree(self._tmp, ignore_errors=True)
        try:
            self._file.close()
        except OSError as exc:
            self.error = self.error or exc
        if self.error is not None:
            reason = "the disk is full" if self.error.errno == errno.ENOSPC else (self.error.strerror or str(self.error))
            raise OutputError(f"cannot write {self.path}: {reason}; the file is incomplete")
