"""darp.calibration: ChArUco calibration of the dual-arm rig (docs/calibration.md).

One module per step: :mod:`~darp.calibration.board` (spec, OpenCV board, printable PDF),
:mod:`~darp.calibration.plan` (capture poses), :mod:`~darp.calibration.capture_run` and
:mod:`~darp.calibration.captures` (taking captures, the capture folder), :mod:`~darp.calibration.detect`
(corners, PnP, rejections), :mod:`~darp.calibration.handeye` (OpenCV hand-eye per arm),
:mod:`~darp.calibration.model` / :mod:`~darp.calibration.jacobian` / :mod:`~darp.calibration.refine`
(joint refinement with identifiability and uncertainty), :mod:`~darp.calibration.world_frame`,
:mod:`~darp.calibration.evaluate` (held-out and truth errors), :mod:`~darp.calibration.solve` (the
driver), :mod:`~darp.calibration.report` (figures), :mod:`~darp.calibration.check` (staleness).
"""
