"""Runtime: device drivers, timing, 3D assembly, recording and replay."""
