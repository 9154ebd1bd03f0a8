"""darp.reconstruction."""
