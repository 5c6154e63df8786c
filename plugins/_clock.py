"""Map a device's clock (camera hardware timestamps, robot controller time) onto the host clock.

Model: ``host = device + offset``, with the offset the smallest ``arrival - device`` seen in a
sliding window (a sample can only arrive after it was taken, so the minimum is the least delayed
sample: the usual one-way offset estimate). A *clock jump* is a step of the device clock that the
host clock did not make: the device advanced by more than ``jump_threshold_s`` more (or less) than
the host did between two samples. On a jump the mapping is re-anchored at once, and
:meth:`map` reports it, so the session logs it and the stamps stay monotonic on the host clock.
"""
from __future__ import annotations

import collections


class ClockMapper:
    """Device time -> host time, robust to transport delay and to device clock jumps.

    Parameters
    ----------
    window : samples kept for the minimum-offset estimate
    jump_threshold_s : a device step that differs from the host step by more than this is a jump
    """

    def __init__(self, window: int = 500, jump_threshold_s: float = 0.25):
        self.window = window
        self.jump_threshold_s = jump_threshold_s
        self._offsets: collections.deque = collections.deque(maxlen=window)
        self._last: tuple[float, float] | None = None   # (device, arrival) of the previous sample
        self.jumps = 0

    def reset(self) -> None:
        """Forget the mapping (after a reconnect the device clock may have restarted)."""
        self._offsets.clear()
        self._last = None

    def map(self, device_t: float, arrival_t: float) -> tuple[float, float | None]:
        """Host stamp of a sample taken at ``device_t`` (s) that arrived at host ``arrival_t`` (s).

        Returns (host stamp, jump) with ``jump`` the size (s) of a detected clock jump, else None.
        """
        jump = None
        if self._last is not None:
            d_device = device_t - self._last[0]
            d_host = arrival_t - self._last[1]
            if abs(d_device - d_host) > self.jump_threshold_s:
                jump = d_device - d_host
                self._offsets.clear()
                self.jumps += 1
        self._last = (device_t, arrival_t)
        self._offsets.append(arrival_t - device_t)
        host = device_t + min(self._offsets)
        return min(host, arrival_t), jump
