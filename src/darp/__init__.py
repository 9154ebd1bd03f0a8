"""darp: calibrated dual-arm eye-in-hand RGB-D-IR robotic perception (the DARP system).

Layers, lowest first: ``errors``, ``geometry``, ``formats`` (on-disk contracts; ``formats.realsense``:
recordings), ``kinematics`` (Z1 model, rig, eq. 1), ``backend``, ``calibration`` / ``acquisition``, ``twin`` /
``hardware`` (backends), ``reconstruction``, ``evaluation``, ``processing``, ``dataset`` / ``export`` / ``view``,
``batch``; ``cli`` sits on top. A layer imports only layers below it: the table in docs/architecture.md is the
rule, and tests/test_architecture.py reads it from there.
"""

from darp.errors import DarpError

__version__ = "0.1.0"
__all__ = ["DarpError", "__version__"]
