"""``nodlidar info``: what is connected - the lidar's VV/PP/II and the servos on the bus.

Without ``--port``/``--servo-port`` it starts the built-in simulated sensor and reports
that.
"""

from __future__ import annotations

import argparse
import json

from ._runtime_args import add_device_args, session_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="device info: lidar VV/PP/II and the servos found",
                       description=__doc__)
    add_device_args(p, design=False, scans=False)
    p.add_argument("--design", metavar="TOML", default=None,
                   help="design of the simulated sensor (default: the paper's build, "
                        "design/urg04lx-paper.toml)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (lidar, params, state, servos, simulated)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.port is not None and args.servo_port is None:
        info = _lidar_only(args.port)  # `nodlidar info --port URL`: just the lidar
    else:
        with session_from_args(args) as s:
            info = s.info()
    v, pp, st = info["version"], info["params"], info["state"]
    out = {"lidar": _plain(v), "params": _plain(pp), "state": _plain(st),
           "servos": info["servos"], "simulated": args.port is None}
    if args.json:
        print(json.dumps(out, indent=2, default=str))
        return 0
    print("lidar (VV):")
    for k, x in out["lidar"].items():
        print(f"  {k:>14}: {x}")
    print("parameters (PP):")
    for k, x in out["params"].items():
        print(f"  {k:>14}: {x}")
    print("state (II):")
    for k, x in out["state"].items():
        print(f"  {k:>14}: {x}")
    if out["servos"] is None:
        print("servos: not queried (no --servo-port)")
        return 0
    print(f"servos found: {len(out['servos'])}")
    for sv in out["servos"]:
        print(f"  id {sv['id']} ({sv['role']}): model {sv['model_number']}, firmware {sv['firmware']}")
    return 0


def _lidar_only(port: str) -> dict:
    from ..runtime.urg import UrgDriver

    with UrgDriver(port) as urg:
        i = urg.info()
    return {"version": i.version, "params": i.params, "state": i.state, "servos": None}


def _plain(obj) -> dict:
    import dataclasses

    if dataclasses.is_dataclass(obj):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if hasattr(obj, "_asdict"):
        return {k: _jsonable(x) for k, x in obj._asdict().items()}
    return {"value": str(obj)}


def _jsonable(x):
    """A JSON value: mappings stay objects (e.g. ``extra``, the unknown fields), sequences
    arrays; anything else its text."""
    if isinstance(x, (int, float, str, bool)) or x is None:
        return x
    if isinstance(x, dict) or hasattr(x, "items"):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return str(x)
