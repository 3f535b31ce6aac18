"""sim/render."""
