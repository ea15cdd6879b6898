"""``nodlidar demo``: the main job on the paper's build, with no hardware needed.

1. solve and verify ``design/urg04lx-paper.toml`` (mirror table, paper comparison);
2. write the design report (HTML + Markdown, drift/interleave/tolerance figures);
3. export the CAD of the mirror mounts (STEP/STL/preview/manifest) into ``cad_out/``;
4. one nod sweep of the built-in simulated sensor (SCIP 2.0 + Dynamixel emulators, ray-traced
   room, the as-built mirrors of the paper's Table I) -> PLY point cloud;
5. calibrate the mirrors against three simulated walls -> calibration TOML + Figure 9;
6. the same sweep through the calibration;
7. the mirror vs no-mirror tracking study (paper Section VI) -> table + figures;

and print where every output went. Steps 4-7 are the ``scan``, ``calibrate`` and ``study``
commands, run in process.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from ._runtime_args import add_design_arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on the paper's build (simulated sensor)",
                       description=__doc__)
    add_design_arg(p)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--cad-out", default="cad_out", help="CAD output root (default cad_out)")
    p.add_argument("--skip", action="append", default=[],
                   choices=["report", "cad", "scan", "calibrate", "study"],
                   help="leave out a step (repeatable)")
    p.set_defaults(func=run)


class _Steps:
    """Numbered step headers with the time each step took."""

    def __init__(self) -> None:
        self.n = 0
        self.t0: float | None = None
        self.outputs: list[tuple[str, Path]] = []

    def start(self, title: str) -> None:
        self.done()
        self.n += 1
        self.t0 = time.perf_counter()
        print(f"\n== {self.n}. {title}", flush=True)

    def done(self) -> None:
        if self.t0 is not None:
            print(f"   ({time.perf_counter() - self.t0:.1f} s)", flush=True)
            self.t0 = None

    def output(self, what: str, path: Path, *, echo: bool = True) -> None:
        self.outputs.append((what, Path(path)))
        if echo:  # the sub-commands print their own "wrote" lines
            print(f"   wrote {path}", flush=True)


def _short(path) -> str:
    """``path`` relative to the working directory when it lies below it (for the echoed
    commands a user may copy), else as given."""
    rel = os.path.relpath(path)
    return str(path) if rel.startswith("..") else rel


def run(args: argparse.Namespace) -> int:
    from ..designio import mirror_table
    from ..solver import solve
    from ..spec import design_to_toml, load_design
    from .design import main_table

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_design(args.design)
    steps = _Steps()

    steps.start(f"design: {spec.name} (solve + verify by ray trace)")
    design = solve(spec)
    print(main_table(design))
    (out / "design.json").write_text(json.dumps(mirror_table(design), indent=2))
    (out / f"{spec.name}.toml").write_text(design_to_toml(spec))
    steps.output("design table", out / "design.json")

    if "report" not in args.skip:
        steps.start("design report (drift, interleave, tolerance Monte Carlo, paper comparison)")
        from ..analysis.report import build_report

        paths = build_report(spec, out / "report")
        steps.output("design report", paths.html)
        print(f"   wrote {paths.markdown} ({len(paths.figures)} figures)")

    if "cad" not in args.skip:
        steps.start("CAD of the mirror mounts (cadquery: STEP, STL, preview, manifest)")
        from ..cad.export import export_cad

        manifest = export_cad(design, args.cad_out)
        steps.output("CAD folder", manifest.folder)

    from ..cli import main as cli

    def command(argv: list[str]) -> None:
        print("   $ nodlidar " + " ".join(argv), flush=True)
        code = cli(argv)
        if code:
            raise SystemExit(code)

    design_arg = _short(args.design)
    sim = ["--design", design_arg, "--sim-rate", "4", "--perturb", "table1"]
    if "scan" not in args.skip:
        steps.start("simulated sensor: one nod sweep, mirrors deployed, as built (Table I), uncalibrated")
        command(["scan", *sim, "--force", "--out", str(out / "scan_uncalibrated.ply")])
        steps.output("point cloud", out / "scan_uncalibrated.ply", echo=False)

    if "calibrate" not in args.skip:
        steps.start("calibration against three simulated walls (paper Section IV)")
        cal = out / "calibration.toml"
        # the demo owns its folder: it clears its last calibration rather than passing
        # calibrate --force, which would also write a calibration whose quality gates failed
        for old in (cal, out / "calibration.png"):
            old.unlink(missing_ok=True)
        command(["calibrate", "--design", design_arg, "--sim", "--perturb", "table1",
                 "--out", str(cal), "--plot", str(out / "calibration.png")])
        steps.output("calibration", cal, echo=False)
        steps.output("calibration plot", out / "calibration.png", echo=False)
        if "scan" not in args.skip:
            steps.start("simulated sensor: the same sweep through the calibration")
            command(["scan", *sim, "--force", "--calibration", str(cal), "--out", str(out / "scan.ply")])
            steps.output("calibrated cloud", out / "scan.ply", echo=False)

    if "study" not in args.skip:
        steps.start("moving-object tracking: mirrors deployed vs lifted (paper Section VI)")
        command(["study", "mirrors", "--design", design_arg, "--force", "--out", str(out / "study")])
        steps.output("tracking study", out / "study" / "study_mirrors.md", echo=False)

    steps.done()
    print("\ndemo outputs:")
    width = max(len(what) for what, _ in steps.outputs) + 2  # >= 2 spaces: the columns stay parseable
    for what, path in steps.outputs:
        print(f"  {what:<{width}}{path.resolve()}")
    return 0
