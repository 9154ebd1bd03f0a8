"""darp.twin."""
