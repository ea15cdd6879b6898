"""Numbers quoted from the paper (Harchowdhury, Kleeman, Vachhani) that code and tests share.

Kept in one place so the simulator (ground truth), calibration (recovery target) and tests
use the same values.
"""

from __future__ import annotations

from types import MappingProxyType

from ._light import PAPER_DESIGN, design_resource
from .geometry import Perturbation

__all__ = ["PAPER_DESIGN", "design_resource", "TABLE_I_PERTURBATIONS", "TRACKING_SPEED_M_S",
           "TRACKING_HEADING_DEG"]



# design_resource and PAPER_DESIGN are defined in nodlidar._light (no numpy: the CLI
# parser needs the default design path; issue 16) and re-exported here

#: Paper Table I: the mounting errors of the four mirrors (dalpha [rad], dbeta [rad],
#: dd [m]), applied with :meth:`nodlidar.geometry.MirrorPatch.perturbed` (conventions.md,
#: "Perturbations"). Read-only mapping mirror name -> Perturbation.
TABLE_I_PERTURBATIONS: MappingProxyType[str, Perturbation] = MappingProxyType({
    "L1": Perturbation(dalpha=-0.043, dbeta=0.05, dd=0.01),
    "L2": Perturbation(dalpha=-0.03, dbeta=0.035, dd=-0.012),
    "R1": Perturbation(dalpha=0.004, dbeta=-0.008, dd=0.007),
    "R2": Perturbation(dalpha=0.03, dbeta=-0.01, dd=-0.005),
})

#: Paper Section VI: the moving obstacle's ground-truth speed [m/s] and heading [deg]
#: (VICON), ``(v, phi) = (0.13 m/s, 89.4 deg)``.
TRACKING_SPEED_M_S = 0.13
TRACKING_HEADING_DEG = 89.4
