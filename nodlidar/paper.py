"""Numbers quoted from the paper (Harchowdhury, Kleeman, Vachhani) that code and tests share.

Kept in one place so the simulator (ground truth), calibration (recovery target) and tests
use the same values.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from types import MappingProxyType

from .geometry import Perturbation

__all__ = ["PAPER_DESIGN", "design_resource", "TABLE_I_PERTURBATIONS", "TRACKING_SPEED_M_S",
           "TRACKING_HEADING_DEG"]



def design_resource(name: str) -> Path:
    """The path of a design file shipped with the package, e.g. ``"urg04lx-paper.toml"`` or
    ``"scenes/paper-tracking.toml"``.

    The files are package data (``nodlidar/designs`` is the repository's ``design/``
    directory), found with :mod:`importlib.resources`, so they are there after a wheel
    install as well as in a checkout, whatever the working directory.
    """
    # a real file on disk: setuptools installs package data unzipped (and the editable
    # install maps the checkout), so the Traversable is a filesystem path.
    return Path(str(files(__package__).joinpath("designs", *name.split("/"))))


#: The paper's build (Section III) as a design file: the default design of every command,
#: a package resource, so it is found from any directory and after a normal install.
PAPER_DESIGN = design_resource("urg04lx-paper.toml")

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
