"""Point-cloud files: PLY/PCD round trips (binary and ASCII) and an independent reader."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar.errors import DesignFileError, ParameterError
from nodlidar.runtime.assembly import PointCloud
from nodlidar.runtime.cloud import read_cloud, read_pcd, read_ply, write_cloud, write_pcd, write_ply


def make_cloud(n: int = 500, seed: int = 1) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud(xyz=rng.normal(0, 3, (n, 3)), t=100.0 + np.sort(rng.random(n)),
                      step=rng.integers(44, 726, n).astype(np.int32),
                      mirror=rng.integers(-1, 4, n).astype(np.int16),
                      scan=np.sort(rng.integers(0, 20, n)).astype(np.int32),
                      range_m=rng.uniform(0.02, 5.6, n), frame="robot",
                      design_name="urg04lx-paper", design_hash="0123abcd",
                      calibration_id="cal-xyz", mirror_names=("L1", "L2", "R1", "R2"),
                      meta={"mirror_moving": 3, "points": n})


def assert_same(a: PointCloud, b: PointCloud, xyz_rtol: float = 0.0) -> None:
    assert_allclose(b.xyz, a.xyz, rtol=xyz_rtol, atol=0)
    assert_array_equal(b.t, a.t)  # float64 written and read bit for bit
    for f in ("step", "mirror", "scan"):
        assert_array_equal(getattr(b, f), getattr(a, f))
    assert_array_equal(b.range_m, a.range_m)
    assert (b.frame, b.design_name, b.design_hash, b.calibration_id, b.mirror_names) == (
        a.frame, a.design_name, a.design_hash, a.calibration_id, a.mirror_names)
    assert dict(b.meta) == dict(a.meta)


@pytest.mark.parametrize("ext", ["ply", "pcd"])
@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_float64_exact(tmp_path, ext, binary):
    c = make_cloud()
    p = write_cloud(tmp_path / f"c.{ext}", c, binary=binary)
    # binary float64 is bit exact; ASCII uses 17 significant digits, also exact
    assert_same(c, read_cloud(p))


@pytest.mark.parametrize("ext", ["ply", "pcd"])
def test_round_trip_float32_xyz(tmp_path, ext):
    c = make_cloud()
    back = read_cloud(write_cloud(tmp_path / f"c.{ext}", c, xyz_type="float32"))
    assert back.xyz.dtype == np.float64
    # float32 keeps 24 bits of mantissa: relative error <= 2**-24 ~ 6e-8
    assert_same(c, back, xyz_rtol=2.0**-24)


def test_file_sizes_match_header(tmp_path):
    c = make_cloud(100)
    p = write_ply(tmp_path / "c.ply", c)
    body = p.read_bytes().split(b"end_header\n", 1)[1]
    assert len(body) == 100 * (3 * 8 + 8 + 4 + 2 + 4 + 8)


def test_trimesh_reads_our_ply(tmp_path):
    """An independent reader (trimesh) sees the same vertices, binary and ASCII."""
    import trimesh

    c = make_cloud(300)
    for binary in (True, False):
        p = write_ply(tmp_path / f"c{int(binary)}.ply", c, binary=binary)
        pc = trimesh.load(p)
        assert isinstance(pc, trimesh.PointCloud)
        assert_allclose(np.asarray(pc.vertices), c.xyz, rtol=0, atol=0)
    p32 = write_ply(tmp_path / "c32.ply", c, xyz_type="float32")
    assert_allclose(np.asarray(trimesh.load(p32).vertices), c.xyz, rtol=2.0**-24, atol=0)


def test_read_pcd_written_by_hand(tmp_path):
    """A minimal PCD from another tool (no nodlidar fields) reads with defaults."""
    p = tmp_path / "x.pcd"
    p.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\n"
                 "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 3\n4.5 5 6\n")
    c = read_pcd(p)
    assert_array_equal(c.xyz, [[1, 2, 3], [4.5, 5, 6]])
    assert c.frame == "sensor" and c.calibration_id == "none"
    assert_array_equal(c.mirror, [-1, -1])


def test_empty_cloud(tmp_path):
    c = make_cloud(0)
    for ext in ("ply", "pcd"):
        for binary in (True, False):
            assert len(read_cloud(write_cloud(tmp_path / f"e{binary}.{ext}", c, binary=binary))) == 0


def test_bad_files(tmp_path):
    with pytest.raises(ParameterError, match="out"):
        write_cloud(tmp_path / "c.xyz", make_cloud(3))
    with pytest.raises(DesignFileError, match="not found"):
        read_ply(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(DesignFileError, match="not a PLY"):
        read_ply(bad)
    p = write_ply(tmp_path / "t.ply", make_cloud(50))
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(DesignFileError, match="truncated"):
        read_ply(p)
    q = write_pcd(tmp_path / "t.pcd", make_cloud(5))
    q.write_bytes(q.read_bytes().replace(b"DATA binary", b"DATA binary_compressed"))
    with pytest.raises(DesignFileError, match="binary_compressed"):
        read_pcd(q)
