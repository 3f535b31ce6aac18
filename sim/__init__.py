"""Optical model and virtual FPP scanner: lenses, rig, scene, Embree tracing, rendering, reconstruction, metrology."""
