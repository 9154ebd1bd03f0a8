"""The twin's RealSense D4xx camera: its specification and per-unit calibration (:mod:`.spec`),
MuJoCo rendering (:mod:`.render`), the sensor that turns renders into depth / IR / colour
(:mod:`.sensor`, with the D4 depth model in :mod:`.depth_model`, stereo matching limits in
:mod:`.stereo`, IR in :mod:`.ir`, noise in :mod:`.noise`), the IMU (:mod:`.imu`), the recording worker
process (:mod:`.worker`) and the backend camera acquisition drives (:mod:`.backend`)."""
