"""The simulator: textured indoor worlds, a camera-carrying vehicle with unknown input disturbances (THESIS.md section 1)."""
