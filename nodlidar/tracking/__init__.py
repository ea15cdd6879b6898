"""Moving-object detection and tracking (paper Sections V-VI).

``simdata`` (scans in the world frame with rays), ``voxels`` (free-space carving),
``segment`` (inconsistent voxels -> dynamic clusters), ``motion`` (centroid estimate and
entropy refinement, eqs 11-13), ``tracker`` (tracks with ids and covariance), ``study``
(mirrors deployed vs lifted, Section VI), ``stonesoup`` (optional converter).
Light to import: numpy/scipy only.
"""
