"""nodlidar: design workbench and runtime for a nodding 2D lidar with reconfigurable mirrors.

The names users need are reachable from here (``nodlidar.__all__``)::

    import nodlidar as nl

    design = nl.solve(nl.load_design(nl.PAPER_DESIGN))
    with nl.Session(sim_rate=5.0) as s:             # no port: the simulated sensor
        cloud = s.sweep().assemble(s.model)
    nl.write_cloud("sweep.ply", cloud)

``import nodlidar`` stays light (standard library only: ``nodlidar --help`` starts fast and
nothing imports numpy, CAD or plotting before it is used): every name, ``__version__`` too,
is resolved on first access (PEP 562 module ``__getattr__``) from the module that defines
it, which is also where its documentation lives. Each name stays importable from that
module too (``from nodlidar.solver import solve``), as the examples do.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any


def _dist_version() -> str:
    """The installed distribution's version (pyproject.toml's [project] version), the
    value of ``nodlidar.__version__``: looked up on first access, because
    importlib.metadata (email, zipfile, csv...) costs every start-up ~40 ms (issue 16)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("nodlidar")
    except PackageNotFoundError:  # pragma: no cover - a checkout on sys.path, never installed
        return "0+unknown"


__version__: str  # declared only: bound by __getattr__ on first access

#: Public name -> the module it is taken from (each lists it in its own ``__all__``).
_LAZY: dict[str, str] = {
    # errors (every error nodlidar raises on purpose is a NodlidarError)
    "NodlidarError": "errors",
    "ParameterError": "errors",
    "DesignFileError": "errors",
    "InfeasibleDesignError": "errors",
    "CalibrationError": "errors",
    "DeviceError": "errors",
    "ProtocolError": "errors",
    # design: spec -> solve -> verify
    "PAPER_DESIGN": "paper",
    "TABLE_I_PERTURBATIONS": "paper",
    "DesignSpec": "spec",
    "load_design": "spec",
    "design_to_toml": "spec",
    "LidarModel": "lidar",
    "lidar_model": "lidar",
    "Perturbation": "geometry",
    "MirrorPatch": "geometry",
    "Design": "solver",
    "MirrorSolution": "solver",
    "solve": "solver",
    "BeamModel": "beams",
    "Verification": "verify",  # (not the function: nodlidar.verify is the module)
    # analyses
    "beam_density": "analysis",
    "interleave": "analysis",
    "bearing_drift": "analysis",
    "Sweep": "analysis.explore",
    "explore": "analysis.explore",
    "tolerance_spec": "analysis.tolerance",
    "monte_carlo": "analysis.tolerance",
    "write_report": "analysis.report",
    # runtime: a session on the sensor (or the simulated one), assembly, clouds, bags
    "Session": "runtime.session",
    "Capture": "runtime.session",
    "record_capture": "runtime.session",
    "AssemblyModel": "runtime.assembly",
    "PointCloud": "runtime.assembly",
    "assemble": "runtime.assembly",
    "write_cloud": "runtime.cloud",
    "read_cloud": "runtime.cloud",
    "BagRecorder": "runtime.bag",
    "read_bag": "runtime.bag",
    "replay_bag": "runtime.bag",
    # calibration
    "calibrate": "calibration",
    "Calibration": "calibration",
    "CalibrationResult": "calibration",
    "WallCapture": "calibration",
    "write_calibration": "calibration",
    "load_calibration": "calibration",
    "simulated_captures": "calibration.synthetic",
    # tracking
    "Tracker": "tracking.tracker",
    "TrackerConfig": "tracking.tracker",
    "TrackState": "tracking.tracker",
    "OnlineSegmenter": "tracking.segment",
    "LiveScans": "tracking.recording",
    # simulation
    "Scene": "sim.scene",
    "load_scene": "sim.scene",
    "builtin_scene": "sim.scene",
    "SceneSimulator": "sim.raycast",
    "SimulatedSensor": "sim.sensor",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use and keep the name here."""
    if name == "__version__":
        globals()[name] = version = _dist_version()
        return version
    try:
        module = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'nodlidar' has no attribute {name!r}") from None
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what type checkers and IDEs see (explicit re-exports); never executed
    from .analysis import beam_density as beam_density
    from .analysis import bearing_drift as bearing_drift
    from .analysis import interleave as interleave
    from .analysis.explore import Sweep as Sweep
    from .analysis.explore import explore as explore
    from .analysis.report import write_report as write_report
    from .analysis.tolerance import monte_carlo as monte_carlo
    from .analysis.tolerance import tolerance_spec as tolerance_spec
    from .beams import BeamModel as BeamModel
    from .calibration import Calibration as Calibration
    from .calibration import CalibrationResult as CalibrationResult
    from .calibration import WallCapture as WallCapture
    from .calibration import calibrate as calibrate
    from .calibration import load_calibration as load_calibration
    from .calibration import write_calibration as write_calibration
    from .calibration.synthetic import simulated_captures as simulated_captures
    from .errors import CalibrationError as CalibrationError
    from .errors import DesignFileError as DesignFileError
    from .errors import DeviceError as DeviceError
    from .errors import InfeasibleDesignError as InfeasibleDesignError
    from .errors import NodlidarError as NodlidarError
    from .errors import ParameterError as ParameterError
    from .errors import ProtocolError as ProtocolError
    from .geometry import MirrorPatch as MirrorPatch
    from .geometry import Perturbation as Perturbation
    from .lidar import LidarModel as LidarModel
    from .lidar import lidar_model as lidar_model
    from .paper import PAPER_DESIGN as PAPER_DESIGN
    from .paper import TABLE_I_PERTURBATIONS as TABLE_I_PERTURBATIONS
    from .runtime.assembly import AssemblyModel as AssemblyModel
    from .runtime.assembly import PointCloud as PointCloud
    from .runtime.assembly import assemble as assemble
    from .runtime.bag import BagRecorder as BagRecorder
    from .runtime.bag import read_bag as read_bag
    from .runtime.bag import replay_bag as replay_bag
    from .runtime.cloud import read_cloud as read_cloud
    from .runtime.cloud import write_cloud as write_cloud
    from .runtime.session import Capture as Capture
    from .runtime.session import Session as Session
    from .runtime.session import record_capture as record_capture
    from .sim.raycast import SceneSimulator as SceneSimulator
    from .sim.scene import Scene as Scene
    from .sim.scene import builtin_scene as builtin_scene
    from .sim.scene import load_scene as load_scene
    from .sim.sensor import SimulatedSensor as SimulatedSensor
    from .solver import Design as Design
    from .solver import MirrorSolution as MirrorSolution
    from .solver import solve as solve
    from .spec import DesignSpec as DesignSpec
    from .spec import design_to_toml as design_to_toml
    from .spec import load_design as load_design
    from .tracking.recording import LiveScans as LiveScans
    from .tracking.segment import OnlineSegmenter as OnlineSegmenter
    from .tracking.tracker import Tracker as Tracker
    from .tracking.tracker import TrackerConfig as TrackerConfig
    from .tracking.tracker import TrackState as TrackState
    from .verify import Verification as Verification
