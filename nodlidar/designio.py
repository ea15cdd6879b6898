"""Plain-data views of a solved design (for JSON output, reports and manifests)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .solver import Design
from .verify import verify

__all__ = ["mirror_table", "paper_comparison"]


def mirror_table(design: Design) -> list[dict[str, Any]]:
    """One dict per mirror with the solver's results and the ray-trace check at D.

    Angles in degrees and lengths in metres, as the key names say.
    """
    summary = verify(design).summary()
    rows = []
    for m in design.mirrors:
        s = summary[m.name]
        rows.append({
            "name": m.name,
            "side": m.side,
            "steps": [m.first_step, m.last_step],
            "beams": int(len(m.steps)),
            "anchor_step": m.anchor_step,
            "offset_index": m.offset_index,
            "length_m": m.length_m,
            "beam_span_m": m.beam_span_m,
            "phi_deg": float(np.degrees(m.phi_rad)),
            "standoff_m": m.standoff_m,
            "oa_m": m.oa_m,
            "oz_m": m.oz_m,
            "normal": [float(x) for x in m.patch.normal],
            "origin_m": [float(x) for x in m.patch.origin],
            "hit_range_m": [float(m.hit_ranges_m.min()), float(m.hit_ranges_m.max())],
            "incidence_deg": [float(np.degrees(m.incidence_rad.min())),
                              float(np.degrees(m.incidence_rad.max()))],
            "rms_error_deg": float(np.degrees(s["rms_error_rad"])),
            "max_error_deg": float(np.degrees(s["max_error_rad"])),
            "blocked_beams": s["blocked"],
        })
    return rows


def paper_comparison(design: Design) -> list[dict[str, Any]]:
    """Rows ``quantity, paper, this design, difference`` for every ``[reference]`` entry.

    Reference keys look like ``L1_length_m`` (compared with the paper's QZ, the span
    between the mirror's first and last beam) or ``L2_phi_deg``.
    """
    rows = []
    for key, paper in sorted(design.spec.reference.items()):
        name, _, quantity = key.partition("_")
        try:
            m = design.mirror(name)
        except KeyError:
            continue
        if quantity == "length_m":
            ours = m.beam_span_m
        elif quantity == "phi_deg":
            ours = float(np.degrees(m.phi_rad))
        else:
            continue
        rows.append({"quantity": key, "paper": float(paper), "ours": ours,
                     "difference": ours - float(paper),
                     "relative": (ours - float(paper)) / float(paper)})
    return rows
