"""librealsense's ``.bag`` layout on top of :mod:`darp.formats.realsense.rosbag1`: the static
description (:mod:`.description`), frames from messages (:mod:`.frames`), chunk bytes
(:mod:`.chunks`), walking messages in order (:mod:`.walk`, fast loops in :mod:`.stream`), the reader
(:mod:`.reader`) and the writer pyrealsense2 plays back (:mod:`.writer`)."""
