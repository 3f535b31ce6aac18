"""Helpers shared by the tests: stores with known LTCs, a fake GigE Vision camera, fuzzing
inputs and an X server."""
