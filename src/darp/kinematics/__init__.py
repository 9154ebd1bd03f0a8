"""darp.kinematics."""
