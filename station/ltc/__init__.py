"""station/ltc."""
