"""Paths and bounds the command line needs to build its parser, in a module that imports
only the standard library: ``nodlidar --help`` must not import numpy (issue 16; it cost
~0.3 s of a 0.46 s start-up). Defined here once; the modules that use them
(:mod:`nodlidar.paper`, :mod:`nodlidar.analysis.tolerance`, :mod:`nodlidar.tracking.recording`)
import them from here and re-export them under their old names.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["PAPER_DESIGN", "design_resource", "MAX_SAMPLES", "DEFAULT_SENSOR_HEIGHT_M"]


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

#: Most Monte Carlo samples one tolerance run takes (:mod:`nodlidar.analysis.tolerance`).
MAX_SAMPLES = 2_000_000

#: Height of the lidar above the ground on the paper's Pioneer mount [m]
#: (:mod:`nodlidar.tracking.recording`).
DEFAULT_SENSOR_HEIGHT_M = 0.4
