"""sim/fpp."""
