"""The ROS2 sqlite recordings (``.db3``) of librealsense >= 2.58: the reader (:mod:`.reader`) and
the pixels of raw and PNG-compressed image messages (:mod:`.images`)."""
