"""``nodlidar cad DESIGN.toml``: export the mirror mounts (STEP, STL, preview, manifest)."""

from __future__ import annotations

import argparse
import json

from ._args import add_force_arg


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "cad", help="export the mirror mounts of a design as STEP/STL + manifest",
        description="Solve a design file and write its mounts (deployed and lifted) to "
                    "OUT/<design name>/: assembly STEPs, printable part STEP+STL, preview, "
                    "manifest.json.")
    p.add_argument("design", help="design TOML file (design/*.toml)")
    p.add_argument("--out", default="cad_out", metavar="DIR",
                   help="output root folder (default: cad_out)")
    p.add_argument("--state", default="both", choices=("both", "deployed", "lifted"),
                   help="assembly state(s) to write (default: both)")
    p.add_argument("--no-preview", action="store_true", help="skip the preview image")
    p.add_argument("--json", action="store_true", help="print the manifest as JSON")
    add_force_arg(p)
    p.set_defaults(func=run)


def _progress_bar():
    """``progress(stage, fraction)`` for :func:`export_cad` drawing a tqdm bar on stderr."""
    from tqdm import tqdm

    bar = tqdm(total=100, desc="CAD export", disable=None, leave=False,
               bar_format="{desc:<32} {percentage:3.0f}%|{bar}| {elapsed}")

    def progress(stage: str, fraction: float) -> None:
        bar.set_description_str(f"CAD export: {stage}", refresh=False)
        bar.update(max(0, round(100 * fraction) - bar.n))

    return progress, bar.close


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..cad.params import mount_params_from_spec
    from ..solver import solve
    from ..spec import load_design
    from ._args import check_output_path

    spec = load_design(args.design)
    params = mount_params_from_spec(spec)        # fail fast on bad [cad] values
    # the one overwrite policy, before the minutes of CAD work: OUT/<name>/ is new or --force
    if Path(args.out).is_dir():  # (a new root is created with its folders by the export)
        check_output_path(Path(args.out) / spec.name, force=args.force, kind="directory")
    design = solve(spec)
    # cadquery only from here on
    from ..cad.export import export_cad

    progress, close = _progress_bar()
    try:
        manifest = export_cad(design, args.out, state=args.state, params=params,
                              preview=not args.no_preview, progress=progress)
    finally:
        close()
    if args.json:
        print(json.dumps(manifest.to_dict(), indent=2))
        return 0
    print(manifest.folder)
    for part in manifest.parts:
        files = ", ".join(part.get("files", [])) or "(reference, in the assemblies)"
        print(f"  {part['name']:<12} {part['kind']:<10} {part['volume_mm3'] / 1000:8.1f} cm3  {files}")
    bed = manifest.parameters["cad"]
    print(f"printed pieces (bed {bed['bed_x_mm']:g} x {bed['bed_y_mm']:g} mm, largest flat face down):")
    for pc in manifest.print_pieces:
        size = " x ".join(f"{x:.0f}" for x in pc["print_size_mm"])
        print(f"  {pc['name']:<12} from {pc['part']:<10} {size:>16} mm  {pc['files'][1]}")
    for r in manifest.print_refused:
        print(f"  not printable on this bed: {r['part']}: {r['reason']}")
    print("bill of materials:")
    for r in manifest.bom:
        print(f"  {r['qty']:>3} x {r['item']:<12} {r['spec']}  ({r['note']})")
    return 0
