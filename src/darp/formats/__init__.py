"""On-disk contracts: RealSense recordings, arm_poses.csv, manip_envelope.json, calibration, surveys.

formats/ knows nothing about robots: it reads and writes files, validates them, and raises
:class:`darp.errors.FormatError` subclasses that name the file and the problem.
"""
