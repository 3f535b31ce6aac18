"""sim/metrology."""
