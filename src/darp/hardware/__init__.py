"""darp.hardware."""
