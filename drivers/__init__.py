"""Hardware interfaces and real device drivers: stage, pattern display, camera."""
