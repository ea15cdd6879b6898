"""Mirror calibration against flat walls (paper Section IV): plane fits, the per-mirror
least-squares fit, calibration files. See :func:`nodlidar.calibration.fit.calibrate`."""

from .calfile import Calibration, load_calibration, write_calibration
from .fit import CalibrationConfig, CalibrationResult, MirrorFit, calibrate, calibration_config
from .walls import Plane, WallCapture, fit_plane

__all__ = ["Calibration", "CalibrationConfig", "CalibrationResult", "MirrorFit", "Plane",
           "WallCapture", "calibrate", "calibration_config", "fit_plane", "load_calibration",
           "write_calibration"]
