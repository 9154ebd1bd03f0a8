"""darp: calibrated dual-arm eye-in-hand RGB-D-IR robotic perception (the DARP system).

Layers, lowest first: ``formats`` (on-disk contracts), ``kinematics`` (Z1 model, rig, eq. 1),
``calibration``, ``acquisition``, ``twin`` / ``hardware`` (backends), ``reconstruction``,
``evaluation``; ``cli`` sits on top. Lower layers never import higher ones.
"""

from darp.errors import DarpError

__version__ = "0.1.0"
__all__ = ["DarpError", "__version__"]
