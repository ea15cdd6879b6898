"""Moving-object detection and tracking (paper Sections V-VI).

``scans`` (ScanPoints: one scan in the world frame with rays), ``simdata`` (simulated
scans), ``voxels`` (free-space carving), ``segment`` (inconsistent voxels -> dynamic
clusters), ``motion`` (centroid estimate and entropy refinement, eqs 11-13), ``tracker``
(multi-object tracker: Kalman filter per track, gating, global assignment), ``study``
(mirrors deployed vs lifted, Section VI), ``evaluate`` (the live tracker online on any
scene: per-mover truth, convergence, purity, switches, GOSPA), ``recording`` (scans from
recordings or live), ``stonesoup`` (optional converter).
Light to import: numpy/scipy only.
"""
