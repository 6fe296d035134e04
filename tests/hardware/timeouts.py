"""Waits shared by the device tests."""

READ_TIMEOUT_S = 1.0
"""Generous wait for a frame that is expected to arrive."""

MISSING_TIMEOUT_S = 0.05
"""Short wait for a frame that is expected not to arrive."""
