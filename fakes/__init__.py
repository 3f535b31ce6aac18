"""Fake hardware: Zaber controller model, fake bench world, fake camera, fake LCD."""
