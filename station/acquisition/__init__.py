"""station/acquisition."""
