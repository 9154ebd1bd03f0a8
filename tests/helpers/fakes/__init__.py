"""Contract-enforcing stand-ins for the vendor SDKs (Unitree ``unitree_arm_interface``, ``pyrealsense2``)."""
