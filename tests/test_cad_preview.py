"""The CAD preview without mplot3d (nodlidar/cad/preview.py, issue 16): its camera against
matplotlib's own 3-D projection, the STL reader against trimesh, the painter's order
in the written image."""

from __future__ import annotations

import numpy as np
import pytest

from nodlidar.cad.preview import PREVIEW_VIEWS, read_stl_triangles, render_preview, view_basis

VIEWS = [(e, a) for e, a, _ in PREVIEW_VIEWS] + [(10.0, 30.0), (-20.0, 140.0), (60.0, -170.0)]


@pytest.mark.parametrize(("elev", "azim"), VIEWS)
def test_view_basis_is_mplot3d_camera(elev, azim):
    """Screen right/up and depth of ``view_basis`` against ``Axes3D.get_proj`` with the
    same ``view_init`` (orthographic, equal box): mplot3d's screen x and y are one common
    scale of ours (no rotation, no shear) and its depth decreases as ours (towards the eye)
    grows. Residuals are float round-off of unit-size coordinates, hence 1e-12."""
    from matplotlib.figure import Figure  # noqa: TID251 (test of the renderer)
    from mpl_toolkits.mplot3d import proj3d

    ax = Figure().add_subplot(projection="3d", proj_type="ortho")
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-1, 1)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    p = np.random.default_rng(0).uniform(-1, 1, (40, 3))
    xs, ys, zs = proj3d.proj_transform(p[:, 0], p[:, 1], p[:, 2], ax.get_proj())
    q = p @ view_basis(elev, azim).T
    B = view_basis(elev, azim)
    np.testing.assert_allclose(B @ B.T, np.eye(3), atol=1e-12)  # orthonormal
    np.testing.assert_allclose(np.linalg.det(B), 1.0, atol=1e-12)  # right-handed
    scale = np.std(xs) / np.std(q[:, 0])
    np.testing.assert_allclose(xs - xs.mean(), scale * (q[:, 0] - q[:, 0].mean()), atol=1e-12)
    np.testing.assert_allclose(ys - ys.mean(), scale * (q[:, 1] - q[:, 1].mean()), atol=1e-12)
    np.testing.assert_allclose(zs - zs.mean(), -scale * (q[:, 2] - q[:, 2].mean()), atol=1e-12)


def test_read_stl_triangles_as_trimesh(tmp_path):
    """Binary STL read with one frombuffer, ASCII through trimesh: both the triangles
    trimesh reads (binary STL stores float32: equal after the same rounding)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=12.5)
    for ascii_ in (False, True):
        path = tmp_path / f"s{int(ascii_)}.stl"
        path.write_bytes(trimesh.exchange.stl.export_stl_ascii(mesh).encode() if ascii_
                         else trimesh.exchange.stl.export_stl(mesh))
        got = read_stl_triangles(path)
        want = np.asarray(trimesh.load(str(path), force="mesh").triangles)
        assert got.shape == (len(mesh.faces), 3, 3) and got.dtype == np.float64
        # trimesh merges vertices on load: compare as sets of triangles
        key = np.round(got.reshape(len(got), -1), 4)
        ref = np.round(want.reshape(len(want), -1), 4)
        assert np.array_equal(np.unique(key, axis=0), np.unique(ref, axis=0))
        np.testing.assert_allclose(got, mesh.triangles, atol=1e-5)  # float32 of 12.5 mm


def _square(z: float, half: float) -> np.ndarray:
    """Two triangles of an axis-aligned square at height ``z`` [mm], shape (2, 3, 3)."""
    c = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    v = np.c_[c, np.full(4, z)]
    return np.stack([v[[0, 1, 2]], v[[0, 2, 3]]])


def test_painters_order_in_the_image(tmp_path):
    """Top view of a small red square 5 mm above a large blue one, listed in either order:
    the centre pixel is red (the nearer face wins), a pixel over the blue square only is
    blue. The top view's light makes horizontal faces 0.45 + 0.55 * 0.8 of their colour."""
    from PIL import Image

    lo, hi = {"lo": _square(0.0, 40.0)}, {"hi": _square(5.0, 10.0)}
    colors = {"lo": (0.0, 0.0, 1.0, 1.0), "hi": (1.0, 0.0, 0.0, 1.0)}
    views = ((90.0, -90.0, "top"),)
    for k, parts in enumerate(({**lo, **hi}, {**hi, **lo})):
        path = tmp_path / f"p{k}.png"
        render_preview({"one": parts}, colors, path, "t", views=views)
        im = np.asarray(Image.open(path).convert("RGB")).astype(float) / 255
        # pixel rows/columns of the data centre and of a point 30 mm right of it
        h, w = im.shape[:2]
        from matplotlib.figure import Figure  # noqa: TID251 (the same layout, no draw)

        fig = Figure(figsize=(5.2, 4.8), dpi=100)
        ax = fig.add_subplot(1, 1, 1)
        fig.subplots_adjust(left=0.06, right=0.98, bottom=0.06, top=0.95)
        pad = 0.06 * 80
        ax.set_xlim(-40 - pad, 40 + pad)
        ax.set_ylim(-40 - pad, 40 + pad)
        ax.set_aspect("equal")
        ax.apply_aspect()
        shade = 0.45 + 0.55 * 0.8 / np.linalg.norm([0.3, -0.5, 0.8])
        for (x, y), want in (((0, 0), (shade, 0, 0)), ((30, 0), (0, 0, shade))):
            px, py = ax.transData.transform((x, y))
            got = im[int(round(h - py)), int(round(px))]
            np.testing.assert_allclose(got, want, atol=2 / 255)  # 8-bit PNG rounding
