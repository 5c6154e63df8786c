"""Former home of the simulator's depth sensor; the models now live in :mod:`app.sim.sensors`.

``SensorModel`` is the default ``independent`` model (:class:`app.sim.sensors.independent.IndependentSensor`:
``sigma(z) = k z^2 + sigma_base``); kept so that existing imports keep working.
"""
from app.sim.sensors.common import depth_edges, smooth_field
from app.sim.sensors.independent import IndependentSensor as SensorModel

__all__ = ["SensorModel", "depth_edges", "smooth_field"]
