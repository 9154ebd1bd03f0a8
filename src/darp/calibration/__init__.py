"""darp.calibration."""
