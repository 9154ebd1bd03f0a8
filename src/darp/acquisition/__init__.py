"""darp.acquisition."""
