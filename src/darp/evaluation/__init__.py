"""darp.evaluation."""
