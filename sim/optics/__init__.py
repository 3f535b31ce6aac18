"""sim/optics."""
