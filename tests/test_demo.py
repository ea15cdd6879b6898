"""``nodlidar demo``: the README's main job runs end to end and writes what it says it wrote."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from nodlidar.cli import main


@pytest.mark.slow
def test_demo_writes_every_output_it_prints(tmp_path, capsys):
    out, cad = tmp_path / "demo", tmp_path / "cad"
    assert main(["demo", "--out", str(out), "--cad-out", str(cad)]) == 0
    text = capsys.readouterr().out
    listed = re.findall(r"^  (\S.*?)\s{2,}(/.+)$", text, flags=re.M)
    names = {what for what, _ in listed}
    assert {"design table", "design report", "CAD folder", "point cloud", "calibration",
            "calibrated cloud", "tracking study"} <= names
    for _, path in listed:
        assert Path(path).exists(), path
    # the report embeds its figures; the CAD manifest lists the mirror faces
    assert "data:image/png;base64," in (out / "report" / "report.html").read_text()
    manifest = json.loads((cad / "urg04lx-paper" / "manifest.json").read_text())
    assert manifest
    assert len(json.loads((out / "design.json").read_text())) >= 4


def test_demo_skip_choices_are_validated(capsys):
    with pytest.raises(SystemExit) as e:
        main(["demo", "--skip", "nonsense"])
    assert e.value.code == 2
