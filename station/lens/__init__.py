"""station/lens."""
