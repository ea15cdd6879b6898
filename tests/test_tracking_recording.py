"""``nodlidar track RECORDING``: a recording of the paper's scene, made by ``nodlidar record``
against the simulated sensor, replays into the tracker and finds the moving cylinder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nodlidar.cli import main
from nodlidar.paper import TRACKING_HEADING_DEG, TRACKING_SPEED_M_S


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "bag"
    # 2x real time: the accuracy budget of the runtime tests holds at this rate under load
    assert main(["record", "--out", str(out), "--scans", "60", "--scene", "paper-tracking",
                 "--sim-rate", "2"]) == 0
    return out


def test_recording_becomes_scan_points(recording):
    from nodlidar.tracking.recording import scans_from_recording

    design, scans = scans_from_recording(recording)
    assert len(scans) >= 55  # a few scans at the ends can fall outside the nod samples
    s = scans[10]
    ok = s.valid
    # a point is start + (r - offset) dir: the ray data and the points agree
    np.testing.assert_allclose(s.ray_start[ok] + (s.range_m[ok] - s.ray_offset[ok])[:, None]
                               * s.ray_dir[ok], s.points[ok], atol=1e-9)
    assert (s.mirror >= 0).any() and (s.mirror == -1).any()  # mirrors deployed while recording
    assert np.all(np.diff(s.steps) > 0)


def test_track_recording_json(recording, capsys):
    assert main(["track", str(recording), "--json"]) == 0
    updates = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    confirmed = [u for u in updates if u.get("confirmed") and u.get("alive")]
    assert confirmed, "no confirmed track"
    last = confirmed[-1]
    # the online tracker after ~15 scans of the object: its own sd is ~0.01 m/s; the issue's
    # tighter bounds (0.01 m/s, 2 deg) are for the full study, tested in test_tracking_study
    assert abs(last["v_m_s"] - TRACKING_SPEED_M_S) < 0.02
    assert abs(last["heading_deg"] - TRACKING_HEADING_DEG) < 4.0


def test_track_missing_recording_is_one_line(tmp_path, capsys):
    assert main(["track", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
