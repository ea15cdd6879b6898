"""Simulated sensor: scene ray casting and device emulators (the default with no hardware)."""
