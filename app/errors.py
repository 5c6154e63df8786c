"""Exceptions shared across osteonav. Each message says what was expected, what arrived and the fix."""
from __future__ import annotations

import math


class OsteonavError(Exception):
    """Base of osteonav's own errors."""


class ConfigError(OsteonavError, ValueError):
    """A configuration value is wrong. The message names the key (dotted path) and the fix."""

    def __init__(self, key: str, message: str, source: str | None = None):
        self.key = key
        self._args = (key, message, source)
        where = f"{source}: " if source else ""
        super().__init__(f"{where}config key '{key}': {message}")

    def __reduce__(self):   # pickled whole: an error raised in a worker process reaches the driver
        return type(self), self._args


class TrialFormatError(OsteonavError, ValueError):
    """A recorded trial does not follow RECORDING_FORMAT.md. Names the file and the line or frame."""

    def __init__(self, path, message: str, location: str | None = None):
        self.path = str(path)
        self.location = location
        self._args = (self.path, message, location)
        loc = f" ({location})" if location else ""
        super().__init__(f"{self.path}{loc}: {message}")

    def __reduce__(self):   # pickled whole: an error raised in a worker process reaches the driver
        return type(self), self._args


class MeshError(OsteonavError, ValueError):
    """A mesh cannot be used for tracking (wrong units, empty, unreadable)."""


class GLError(OsteonavError, RuntimeError):
    """OpenGL context or shader failure; the message names the file, the stage and the driver log."""


def megabytes(value, key: str, example: float, zero_means: str | None = None) -> float:
    """``value`` as a memory budget in megabytes for the configuration key ``key``, else a ConfigError naming
    it and ``example``: a finite number > 0, or >= 0 when ``zero_means`` says what 0 does. Text and booleans
    are refused (YAML gives numbers)."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not (number and (value > 0 or (zero_means is not None and value == 0))):
        bound = "positive number" if zero_means is None else f"number >= 0 (0: {zero_means})"
        raise ConfigError(key, f"expected a {bound} of megabytes, e.g. {example:g}; got {value!r}")
    return float(value)
