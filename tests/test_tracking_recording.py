"""``nodlidar track RECORDING`` and ``nodlidar track live``: a recording of the paper's scene,
made by ``nodlidar record`` against the simulated sensor, replays into the tracker and finds
the moving cylinder; the same live from a runtime session."""

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


def test_recording_scan_points_are_the_assembly_cloud(recording):
    # the tracking's scans come out of the runtime assembly itself: the returned beams are
    # exactly replay_bag's cloud (same beams, same order, same coordinates), the no-return
    # beams are kept on top of it (NaN) for free-space carving
    from nodlidar.runtime.bag import replay_bag
    from nodlidar.tracking.recording import scans_from_recording

    _, cloud = replay_bag(recording)
    _, scans = scans_from_recording(recording, sensor_height_m=0.0)
    pts = np.concatenate([s.points[s.valid] for s in scans])
    t = np.concatenate([s.t_s[s.valid] for s in scans])
    np.testing.assert_array_equal(pts, cloud.xyz)
    np.testing.assert_array_equal(t, cloud.t)
    n_nan = sum(int((~s.valid).sum()) for s in scans)
    assert n_nan > 0 and n_nan <= cloud.meta["error_codes"]
    assert {s.calibration_id for s in scans} == {cloud.calibration_id}


def test_recording_floor_is_at_zero(recording):
    # the paper scene's sensor is 0.4 m above the floor; raised by the default sensor
    # height, the floor returns (the lowest surface) sit at z = 0 where the ground removal
    # expects them (the URG's 1 cm noise; grazing floor hits lie within a few cm)
    from nodlidar.tracking.recording import scans_from_recording

    _, scans = scans_from_recording(recording)
    z = np.concatenate([s.points[s.valid, 2] for s in scans])
    assert abs(np.percentile(z, 1)) < 0.03
    assert np.mean(np.abs(z) < 0.05) > 0.3  # a large part of the returns is floor


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


def test_track_live_simulated_sensor(capsys, tmp_path):
    # live: the simulated sensor (as built with Table I) over its emulated links through a
    # runtime session with a calibration (here Table I itself), each scan assembled once the
    # servo samples cover it and tracked as it arrives
    from nodlidar.calibration.calfile import Calibration, write_calibration
    from nodlidar.calibration.fit import design_hash
    from nodlidar.paper import TABLE_I_PERTURBATIONS
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    spec = solve(load_design("design/urg04lx-paper.toml")).spec
    write_calibration(tmp_path / "cal.toml", Calibration(
        id="cal-truth", design_name=spec.name, design_hash=design_hash(spec), created="",
        model="exact", perturbations=dict(TABLE_I_PERTURBATIONS)))
    assert main(["track", "live", "--scans", "45", "--sim-rate", "2", "--json", "--perturb",
                 "table1", "--calibration", str(tmp_path / "cal.toml")]) == 0
    out = capsys.readouterr()
    updates = [json.loads(line) for line in out.out.splitlines()]
    confirmed = [u for u in updates if u.get("confirmed") and u.get("alive")]
    assert confirmed, "no confirmed track"
    last = confirmed[-1]
    # same bounds and reason as the recording above
    assert abs(last["v_m_s"] - TRACKING_SPEED_M_S) < 0.02
    assert abs(last["heading_deg"] - TRACKING_HEADING_DEG) < 4.0
    done = [line for line in out.err.splitlines() if line.startswith("live: tracked")]
    n_done, n_in = (int(w) for w in done[0].split()[2:5:2])
    assert n_in == 45 and n_done >= 43  # scans at the very ends may lack nod samples
    assert "calibration cal-truth" in done[0]


def test_track_live_port_needs_live(capsys):
    assert main(["track", "--port", "/dev/null", "--servo-port", "/dev/null"]) == 2
    assert "live" in capsys.readouterr().err


def test_track_missing_recording_is_one_line(tmp_path, capsys):
    assert main(["track", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1


def test_live_scans_equal_the_whole_capture_assembled_at_once():
    # LiveScans hands a scan on only once every servo's samples reach past its last beam, so
    # the interpolation sees the same bracketing samples as after the capture: scan by scan
    # it must give exactly what the whole capture gives at once
    from nodlidar.runtime.session import Session
    from nodlidar.tracking.recording import LiveScans, scans_from_capture

    got = []
    with Session(scene="paper-tracking", sim_rate=2, log=None) as s:
        live = LiveScans(s.model, (s.lift_left, s.lift_right))
        cap = s.capture(lambda scans, _nod: len(scans) >= 12,
                        on_scan=lambda scan, smp: got.extend(live.on_scan(scan, smp)))
        n_live = len(got)
        got += live.finish(cap)
        whole = scans_from_capture(s.model, cap.scans, cap.joints, (s.lift_left, s.lift_right))
    assert n_live >= 9  # most scans were handed on during the capture, one scan behind
    assert [g.scan for g in got] == [w.scan for w in whole]
    for g, w in zip(got, whole):
        np.testing.assert_array_equal(g.steps, w.steps)
        np.testing.assert_array_equal(g.points, w.points)
        np.testing.assert_array_equal(g.ray_dir, w.ray_dir)


def test_live_scans_with_pruned_samples_equal_the_whole_capture():
    """``track live``'s way: a capture that keeps no scans, samplers pruned behind
    ``LiveScans.need_since_s()`` after every scan. The scans handed on equal the whole
    capture assembled at once from every sample (collected here before each prune), and the
    samplers hold only a few scans' worth at any time (memory flat over a long run)."""
    from nodlidar.runtime.session import Session
    from nodlidar.tracking.recording import LiveScans, scans_from_capture

    got, scans, seen, held = [], [], {}, []
    with Session(scene="paper-tracking", sim_rate=2, log=None) as s:
        live = LiveScans(s.model, (s.lift_left, s.lift_right))

        def on_scan(scan, samplers):
            scans.append(scan)
            for name, smp in samplers.items():   # every sample, before it can be pruned
                x = smp.samples()
                t, a = seen.get(name, (np.empty(0), np.empty(0)))
                new = x.host_time_s > (t[-1] if len(t) else -np.inf)
                seen[name] = (np.r_[t, x.host_time_s[new]], np.r_[a, x.angle_rad[new]])
            got.extend(live.on_scan(scan, samplers))
            for smp in samplers.values():
                smp.prune(live.need_since_s())
                held.append(len(smp.buffer))

        cap = s.capture(lambda sc, _nod: len(sc) >= 14, on_scan=on_scan, keep=False)
        for name, (t, a) in cap.joints.items():   # what came after the last scan
            tt, aa = seen[name]
            new = t > tt[-1]
            seen[name] = (np.r_[tt, t[new]], np.r_[aa, a[new]])
        got += live.finish(cap)
        whole = scans_from_capture(s.model, scans, seen, (s.lift_left, s.lift_right))
    assert [g.scan for g in got] == [w.scan for w in whole] and len(got) == 14
    for g, w in zip(got, whole):
        np.testing.assert_array_equal(g.points, w.points)
        np.testing.assert_array_equal(g.steps, w.steps)
    # a scan is 0.1 s; the nod and lift samplers read tens of samples a second each: far
    # fewer than the whole run's samples stay buffered once pruning works
    total = max(len(t) for t, _ in seen.values())
    assert max(held) < 0.5 * total
