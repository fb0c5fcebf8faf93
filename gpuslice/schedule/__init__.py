"""Stage 3, the layer schedule: uniform and explicit (``uniform.py``), adaptive (``adaptive.py`` +
``kernels/adaptive.cl``)."""

from .adaptive import ADAPTIVE_MODES, AdaptiveSchedule, adaptive_schedule, cusp_schedule
from .uniform import Schedule, from_z, uniform

__all__ = [
    "ADAPTIVE_MODES",
    "AdaptiveSchedule",
    "Schedule",
    "adaptive_schedule",
    "cusp_schedule",
    "from_z",
    "uniform",
]
