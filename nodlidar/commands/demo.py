"""``nodlidar demo``: the main job on the paper's build, with no hardware needed.

Solves and verifies design/urg04lx-paper.toml and says where the outputs went. (The design
report, CAD export and simulated scan join this job as their issues land.)
"""

from __future__ import annotations

import json
from pathlib import Path

DEFAULT_DESIGN = "design/urg04lx-paper.toml"


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the paper's build (simulated sensor)",
                       description=__doc__)
    p.add_argument("--design", default=DEFAULT_DESIGN, help=f"design file (default {DEFAULT_DESIGN})")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--cad-out", default="cad_out", help="CAD output root (default cad_out)")
    p.set_defaults(func=run)


def _step(title: str) -> None:
    print(f"\n== {title}", flush=True)


def run(args) -> int:
    from ..designio import mirror_table
    from ..solver import solve
    from ..spec import design_to_toml, load_design

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_design(args.design)

    _step(f"design: {spec.name}")
    from .design import main_table

    design = solve(spec)
    print(main_table(design))
    (out / "design.json").write_text(json.dumps(mirror_table(design), indent=2))
    (out / f"{spec.name}.toml").write_text(design_to_toml(spec))
    print(f"wrote {out / 'design.json'}")

    print(f"\ndemo outputs: {out.resolve()}")
    return 0
