"""Export of the mirror mounts: STEP/STL files, preview image and a JSON manifest.

``export_cad(design, "cad_out")`` writes ``cad_out/<design name>/``::

    assembly_deployed.step, assembly_lifted.step   named, coloured assemblies (mm)
    parts/<part>.step, parts/<part>.stl            each printable part (head frame, deployed)
    print/<piece>.step, print/<piece>.stl          the parts split to fit the printer bed,
                                                    each in its print orientation
    bom.md                                          bill of materials and the print list
    meshes/<state>/<part>.stl                       every part in each state (validation, preview)
    preview.png                                     both states, rendered from the STL triangles
    manifest.json                                   parameters, parts, mirror face poses, files

Library code never prints; pass ``progress=callable(stage: str, fraction: float)`` to
follow the export.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .mounts import (
    STATES,
    MountModel,
    build_assembly,
    build_mounts,
    mirror_face_poses,
    part_shapes,
)
from .params import MountParams, mount_params_from_spec
from .preview import PREVIEW_VIEWS, read_stl_triangles, render_preview  # noqa: F401 (API)

__all__ = ["Manifest", "export_cad", "MANIFEST_NAME"]

MANIFEST_NAME = "manifest.json"
Progress = Callable[[str, float], None]


@dataclass(frozen=True)
class Manifest:
    """What :func:`export_cad` wrote (paths relative to :attr:`folder`)."""

    folder: Path
    design_name: str
    states: tuple[str, ...]
    parts: list[dict[str, Any]]
    mirror_faces: dict[str, dict[str, dict[str, Any]]]
    hinge_axes: dict[str, dict[str, Any]]
    parameters: dict[str, Any]
    files: list[str] = field(default_factory=list)
    print_pieces: list[dict[str, Any]] = field(default_factory=list)
    print_refused: list[dict[str, str]] = field(default_factory=list)
    bom: list[dict[str, Any]] = field(default_factory=list)

    @property
    def path(self) -> Path:
        """The manifest file."""
        return self.folder / MANIFEST_NAME

    def file(self, rel: str) -> Path:
        return self.folder / rel

    def printable_parts(self) -> list[str]:
        return [p["name"] for p in self.parts if p["kind"] == "printable"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "design": self.design_name,
            "units": {"length": "mm", "frame": "head frame: x forward, y left, z up, "
                      "scan plane z = 0, lidar optical axis = z"},
            "states": list(self.states),
            "parameters": self.parameters,
            "parts": self.parts,
            "hinge_axes": self.hinge_axes,
            "mirror_faces": self.mirror_faces,
            "files": self.files,
            "print": {"bed_mm": [self.parameters.get("cad", {}).get("bed_x_mm"),
                                 self.parameters.get("cad", {}).get("bed_y_mm")],
                      "pieces": self.print_pieces, "refused": self.print_refused},
            "bom": self.bom,
        }

    @classmethod
    def load(cls, folder: str | Path) -> Manifest:
        folder = Path(folder)
        d = json.loads((folder / MANIFEST_NAME).read_text())
        return cls(folder=folder, design_name=d["design"], states=tuple(d["states"]),
                   parts=d["parts"], mirror_faces=d["mirror_faces"],
                   hinge_axes=d["hinge_axes"], parameters=d["parameters"], files=d["files"],
                   print_pieces=d.get("print", {}).get("pieces", []), bom=d.get("bom", []),
                   print_refused=d.get("print", {}).get("refused", []))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _bom_markdown(name: str, bom: list[dict[str, Any]], pieces: list[dict[str, Any]],
                  P: MountParams, refused: list[dict[str, str]]) -> str:
    """The bill of materials and the print list as Markdown (``bom.md``)."""
    lines = [f"# {name}: bill of materials", "", "| item | spec | qty | note |", "|---|---|---|---|"]
    lines += [f"| {r['item']} | {r['spec']} | {r['qty']} | {r['note']} |" for r in bom]
    lines += ["", f"## Printed pieces (bed {P.bed_x_mm:g} x {P.bed_y_mm:g} mm, largest flat face "
              "down)", "", "| piece | from part | size on the bed [mm] | joints |", "|---|---|---|---|"]
    for pc in pieces:
        sz = " x ".join(f"{x:.1f}" for x in pc["print_size_mm"])
        joints = "; ".join(f"half lap with {', '.join(n for n in j['pieces'] if n != pc['name'])}"
                           for j in pc["joints"]) or "-"
        lines.append(f"| {pc['name']} | {pc['part']} | {sz} | {joints} |")
    lines += [f"\nNot printable on this bed: {r['part']}: {r['reason']}" for r in refused]
    return "\n".join(lines) + "\n"


def export_cad(design: Any, out_dir: str | Path = "cad_out", *, state: str = "both",
               params: MountParams | None = None, preview: bool = True,
               progress: Progress | None = None) -> Manifest:
    """Build the mounts of ``design`` and write them to ``out_dir/<design name>/``.

    Parameters
    ----------
    design : nodlidar.solver.Design
        A solved design.
    out_dir : path
        Root output folder (``cad_out``); the design's own folder is created inside.
    state : {"both", "deployed", "lifted"}
        Which assembly states to write (printable parts are always written as built).
    params : MountParams, optional
        Fabrication parameters; default: the design file's ``[cad]`` table.
    preview : bool
        Render ``preview.png``.
    progress : callable, optional
        Called as ``progress(stage, fraction)``.

    Returns
    -------
    Manifest
    """
    import cadquery as cq  # noqa: TID251 (lazy: only when CAD is asked for)

    from ..errors import ParameterError

    if state not in ("both", *STATES):
        raise ParameterError("state", state, "both, deployed or lifted")
    states = STATES if state == "both" else (state,)
    report = progress or (lambda stage, frac: None)
    P = params or mount_params_from_spec(design.spec)
    folder = Path(out_dir) / design.spec.name
    files: list[str] = []

    report("build", 0.0)
    model: MountModel = build_mounts(design, P)    # raises before anything is written
    (folder / "parts").mkdir(parents=True, exist_ok=True)
    tol, atol = P.stl_tolerance_mm, P.stl_angular_tolerance_rad
    parts_info: list[dict[str, Any]] = []
    n_steps = len(model.parts) + 2 * len(states) + 3
    done = 0

    def tick(stage: str) -> None:
        nonlocal done
        done += 1
        report(stage, min(done / n_steps, 1.0))

    for p in model.parts:
        bb = p.shape.BoundingBox()
        info: dict[str, Any] = {
            "name": p.name, "kind": p.kind, "side": p.side, "description": p.description,
            "volume_mm3": float(p.shape.Volume()),
            "bbox_mm": [[bb.xmin, bb.ymin, bb.zmin], [bb.xmax, bb.ymax, bb.zmax]],
            "faces": len(p.shape.Faces()),
        }
        if p.kind == "printable":
            step, stl = f"parts/{p.name}.step", f"parts/{p.name}.stl"
            # one STEP product, named after the part (a plain export names it after OCCT)
            cq.Assembly(p.shape, name=p.name).export(str(folder / step), mode="fused")
            cq.exporters.export(p.shape, str(folder / stl), tolerance=tol, angularTolerance=atol)
            info["files"] = [step, stl]
            files += [step, stl]
        parts_info.append(info)
        tick(f"part {p.name}")

    meshes: dict[str, dict[str, Any]] = {}
    for st in states:
        assy = build_assembly(model, st)
        rel = f"assembly_{st}.step"
        assy.export(str(folder / rel))
        files.append(rel)
        tick(f"assembly {st}")
        (folder / "meshes" / st).mkdir(parents=True, exist_ok=True)
        meshes[st] = {}
        for name, shape in part_shapes(model, st).items():
            rel = f"meshes/{st}/{name}.stl"
            cq.exporters.export(shape, str(folder / rel), tolerance=tol, angularTolerance=atol)
            files.append(rel)
            if preview:
                meshes[st][name] = read_stl_triangles(folder / rel)
        tick(f"meshes {st}")

    # printable pieces: split to fit the bed, each in its print orientation, STEP products
    # named after the pieces; and the bill of materials
    from .printable import bill_of_materials, print_pieces

    refused: list[dict[str, str]] = []   # parts no cut makes fit: said in the manifest
    pieces = print_pieces(model, P, refused=refused)
    (folder / "print").mkdir(exist_ok=True)
    pieces_info = []
    for pc in pieces:
        step, stl = f"print/{pc.name}.step", f"print/{pc.name}.stl"
        cq.Assembly(pc.printed, name=pc.name).export(str(folder / step), mode="fused")
        cq.exporters.export(pc.printed, str(folder / stl), tolerance=tol, angularTolerance=atol)
        files += [step, stl]
        pieces_info.append({**pc.to_dict(), "files": [step, stl],
                            "volume_mm3": float(pc.printed.Volume())})
    bom = bill_of_materials(design, P, pieces)
    (folder / "bom.md").write_text(_bom_markdown(design.spec.name, bom, pieces_info, P, refused))
    files.append("bom.md")
    tick("print pieces")

    if preview:
        colors = {p.name: p.color for p in model.parts}
        render_preview(meshes, colors, folder / "preview.png", design.spec.name)
        files.append("preview.png")
    tick("preview")

    poses = mirror_face_poses(design, P)
    poses = {m: {s: v for s, v in st.items() if s in states} for m, st in poses.items()}
    manifest = Manifest(
        folder=folder, design_name=design.spec.name, states=tuple(states), parts=parts_info,
        mirror_faces=poses, hinge_axes={s: a.to_dict() for s, a in model.axes.items()},
        parameters={"design": _jsonable(design.spec.to_dict()), "cad": P.to_dict(),
                    "derived_mm": _jsonable(model.extras)},
        files=[*files, MANIFEST_NAME], print_pieces=pieces_info, bom=bom,
        print_refused=refused,
    )
    manifest.path.write_text(json.dumps(_jsonable(manifest.to_dict()), indent=2))
    tick("manifest")
    report("done", 1.0)
    return manifest
