"""Geometry conventions against rays worked out by hand, and every invalid-geometry path.

The expected numbers below come from the conventions in docs/conventions.md, written
out per angle (source on +x at a = 0, e_u = (-sin a, cos a, 0), e_v = -z, pixel centres at
(i + 0.5 - n/2) * pixel size), not from ``Geometry.rays``.
"""
import math

import numpy as np
import pytest

from mi_grg.core.geometry import Geometry, GeometryError, circular_angles

# A small scanner whose pixel centres are round numbers: 3 x 5 pixels of 0.5 x 0.5, so the
# row offsets along e_v are (i - 1) * 0.5 and the column offsets along e_u are (j - 2) * 0.5.
DSD, DSO = 7.0, 5.0
BASE = dict(DSD=DSD, DSO=DSO, nDetector=(3, 5), sDetector=(1.5, 2.5), nVoxel=(4, 4, 4),
            sVoxel=(2.0, 2.0, 2.0))
CORNERS_AND_CENTRE = [(0, 0), (0, 4), (2, 0), (2, 4), (1, 2)]


def _geo(mode="cone", angles=(0.0,), **kw):
    args = dict(BASE, mode=mode, angles=angles)
    args.update(kw)
    return Geometry(**args)


# Hand-computed pixel centres (x, y, z) for the pixels in CORNERS_AND_CENTRE.
PIXELS = {
    # a = 0: detector centre (-2, 0, 0), e_u = (0, 1, 0), e_v = (0, 0, -1)
    0.0: [(-2, -1, 0.5), (-2, 1, 0.5), (-2, -1, -0.5), (-2, 1, -0.5), (-2, 0, 0)],
    # a = pi/2: detector centre (0, -2, 0), e_u = (-1, 0, 0)
    math.pi / 2: [(1, -2, 0.5), (-1, -2, 0.5), (1, -2, -0.5), (-1, -2, -0.5), (0, -2, 0)],
    # a = pi: detector centre (2, 0, 0), e_u = (0, -1, 0)
    math.pi: [(2, 1, 0.5), (2, -1, 0.5), (2, 1, -0.5), (2, -1, -0.5), (2, 0, 0)],
}
SOURCES = {0.0: (5, 0, 0), math.pi / 2: (0, 5, 0), math.pi: (-5, 0, 0)}
# With offDetector = (0.2, -0.4) at a = pi/2 the detector centre moves by 0.2 e_v - 0.4 e_u
# = (0.4, 0, -0.2): centre (0.4, -2, -0.2).
PIXELS_OFFSET_HALF_PI = [(1.4, -2, 0.3), (-0.6, -2, 0.3), (1.4, -2, -0.7), (-0.6, -2, -0.7),
                         (0.4, -2, -0.2)]


def _odd_angle_pixel(a, i, j, off=(0.0, 0.0)):
    """Pixel centre at an arbitrary angle, written from the conventions."""
    c, s = math.cos(a), math.sin(a)
    su, sv = (j - 2) * 0.5 + off[1], (i - 1) * 0.5 + off[0]
    return np.array([-(DSD - DSO) * c - su * s, -(DSD - DSO) * s + su * c, -sv])


def _rays_at(geo, a, pixels):
    i, j = np.array(pixels).T
    o, d, length = geo.rays(np.full(i.shape, math.cos(a)), np.full(i.shape, math.sin(a)),
                            i + 0.5, j + 0.5)
    bc = lambda t: np.stack(np.broadcast_arrays(*t), -1)  # noqa: E731
    return bc(o), bc(d), np.broadcast_to(length, i.shape)


@pytest.mark.parametrize("a", list(PIXELS))
def test_cone_rays_by_hand(a):
    geo = _geo("cone", angles=(a,))
    o, d, length = _rays_at(geo, a, CORNERS_AND_CENTRE)
    pix = np.array(PIXELS[a], float)
    src = np.array(SOURCES[a], float)
    np.testing.assert_allclose(o, np.broadcast_to(src, o.shape), atol=1e-12)
    want = (pix - src) / np.linalg.norm(pix - src, axis=1, keepdims=True)
    np.testing.assert_allclose(d, want, atol=1e-12)
    np.testing.assert_allclose(length, np.linalg.norm(pix - src, axis=1), atol=1e-12)
    # the centre pixel's ray is the central ray, straight through the rotation axis
    np.testing.assert_allclose(d[-1], -src / DSO, atol=1e-12)


def test_cone_rays_with_detector_offset_by_hand():
    a = math.pi / 2
    geo = _geo("cone", angles=(a,), offDetector=(0.2, -0.4))
    o, d, _ = _rays_at(geo, a, CORNERS_AND_CENTRE)
    pix = np.array(PIXELS_OFFSET_HALF_PI)
    src = np.array([0.0, 5.0, 0.0])
    np.testing.assert_allclose(o, np.broadcast_to(src, o.shape), atol=1e-12)
    np.testing.assert_allclose(d, (pix - src) / np.linalg.norm(pix - src, axis=1)[:, None],
                               atol=1e-12)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
@pytest.mark.parametrize("off", [(0.0, 0.0), (0.2, -0.4)])
def test_odd_angle(mode, off):
    a = 0.3
    geo = _geo(mode, angles=(a,), offDetector=off, offOrigin=(0.1, -0.2, 0.3))
    o, d, length = _rays_at(geo, a, CORNERS_AND_CENTRE)
    pix = np.array([_odd_angle_pixel(a, i, j, off) for i, j in CORNERS_AND_CENTRE])
    normal = np.array([math.cos(a), math.sin(a), 0.0])
    if mode == "cone":
        src = DSO * normal
        want_d = (pix - src) / np.linalg.norm(pix - src, axis=1, keepdims=True)
        np.testing.assert_allclose(o, np.broadcast_to(src, o.shape), atol=1e-12)
    else:
        want_d = np.broadcast_to(-normal, pix.shape)
        np.testing.assert_allclose(o, pix + DSD * normal, atol=1e-12)
    np.testing.assert_allclose(d, want_d, atol=1e-12)
    # every ray reaches its pixel centre after `length`
    np.testing.assert_allclose(o + length[:, None] * d, pix, atol=1e-12)


@pytest.mark.parametrize("a", list(PIXELS))
def test_parallel_rays_by_hand(a):
    geo = _geo("parallel", angles=(a,))
    o, d, length = _rays_at(geo, a, CORNERS_AND_CENTRE)
    pix = np.array(PIXELS[a], float)
    back = {0.0: (-1, 0, 0), math.pi / 2: (0, -1, 0), math.pi: (1, 0, 0)}[a]
    np.testing.assert_allclose(d, np.broadcast_to(back, d.shape), atol=1e-12)
    np.testing.assert_allclose(o, pix - DSD * np.array(back, float), atol=1e-12)
    np.testing.assert_allclose(length, DSD)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_pixel_rays_numpy_layout(mode):
    """[view, v, u] order: view k, row i, column j is the hand-computed pixel."""
    angles = [0.0, math.pi / 2, math.pi, 0.3]
    geo = _geo(mode, angles=angles)
    o, d = geo.pixel_rays_numpy()
    assert o.shape == d.shape == (4, 3, 5, 3)
    for k, a in enumerate(angles):
        for n, (i, j) in enumerate(CORNERS_AND_CENTRE):
            pix = np.array(PIXELS[a][n], float) if a in PIXELS else _odd_angle_pixel(a, i, j)
            normal = np.array([math.cos(a), math.sin(a), 0.0])
            if mode == "cone":
                want = (pix - DSO * normal) / np.linalg.norm(pix - DSO * normal)
            else:
                want = -normal
            np.testing.assert_allclose(d[k, i, j], want, atol=1e-12)
            # the ray passes through the pixel centre
            t = np.dot(pix - o[k, i, j], d[k, i, j])
            np.testing.assert_allclose(o[k, i, j] + t * d[k, i, j], pix, atol=1e-12)


def test_detector_frame_by_hand():
    geo = _geo("cone", angles=(0.0, math.pi / 2, math.pi), offDetector=(0.2, -0.4))
    f = geo.detector_frame()
    np.testing.assert_allclose(f["source"], [[5, 0, 0], [0, 5, 0], [-5, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(f["e_u"], [[0, 1, 0], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(f["e_v"], [[0, 0, -1]] * 3, atol=1e-12)
    np.testing.assert_allclose(f["normal"], [[1, 0, 0], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    # centre: -(DSD - DSO) * normal + 0.2 * e_v - 0.4 * e_u
    np.testing.assert_allclose(f["center"], [[-2, -0.4, -0.2], [0.4, -2, -0.2],
                                             [2, 0.4, -0.2]], atol=1e-12)
    # explicit angles override the geometry's
    g = geo.detector_frame(angles=[math.pi / 2])
    np.testing.assert_allclose(g["source"], [[0, 5, 0]], atol=1e-12)


def test_rays_ignore_the_volume_offset():
    """offOrigin moves the volume, not the scanner."""
    a = [0.0, 0.3, 2.0]
    o1, d1 = _geo(angles=a).pixel_rays_numpy()
    o2, d2 = _geo(angles=a, offOrigin=(0.1, -0.2, 0.3)).pixel_rays_numpy()
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(d1, d2)


def test_voxel_axes_and_spacings():
    geo = Geometry(mode="cone", DSD=20.0, DSO=10.0, nDetector=(4, 8), sDetector=(2.0, 6.0),
                   nVoxel=(2, 3, 4), sVoxel=(2.0, 3.0, 4.0), offOrigin=(0.5, 0.0, -1.0),
                   angles=[0.0])
    x, y, z = geo.voxel_axes()
    np.testing.assert_allclose(x, [0.0, 1.0])
    np.testing.assert_allclose(y, [-1.0, 0.0, 1.0])
    np.testing.assert_allclose(z, [-2.5, -1.5, -0.5, 0.5])
    assert geo.dVoxel == (1.0, 1.0, 1.0)
    assert geo.dDetector == (0.5, 0.75)
    np.testing.assert_allclose(geo.bbox(), [[-0.5, -1.5, -3.0], [1.5, 1.5, 1.0]])
    assert geo.projection_shape == (1, 4, 8)
    assert geo.scene_scale == pytest.approx(0.5)


@pytest.mark.parametrize("mode", ["cone", "parallel"])
def test_scaled(mode):
    geo = _geo(mode, angles=[0.0, 0.3, 2.0], offDetector=(0.2, -0.4),
               offOrigin=(0.1, -0.2, 0.3))
    f = 2.5
    s = geo.scaled(f)
    assert (s.DSD, s.DSO) == (DSD * f, DSO * f)
    np.testing.assert_allclose(s.sDetector, np.multiply(geo.sDetector, f))
    np.testing.assert_allclose(s.sVoxel, np.multiply(geo.sVoxel, f))
    np.testing.assert_allclose(s.offOrigin, np.multiply(geo.offOrigin, f))
    np.testing.assert_allclose(s.offDetector, np.multiply(geo.offDetector, f))
    assert s.nDetector == geo.nDetector and s.nVoxel == geo.nVoxel
    np.testing.assert_array_equal(s.angles, geo.angles)
    o1, d1 = geo.pixel_rays_numpy()
    o2, d2 = s.pixel_rays_numpy()
    np.testing.assert_allclose(o2, f * o1, atol=1e-12)   # a similarity: same directions
    np.testing.assert_allclose(d2, d1, atol=1e-12)


def test_scanner_dict_round_trip():
    geo = _geo("cone", angles=circular_angles(7), offDetector=(0.2, -0.4),
               offOrigin=(0.1, -0.2, 0.3))
    d = geo.to_scanner_dict()
    assert d["dDetector"] == [0.5, 0.5] and d["dVoxel"] == [0.5, 0.5, 0.5]
    back = Geometry.from_scanner_dict(d, geo.angles)
    for name in ("mode", "DSD", "DSO", "nDetector", "sDetector", "nVoxel", "sVoxel",
                 "offOrigin", "offDetector"):
        assert getattr(back, name) == getattr(geo, name), name
    np.testing.assert_array_equal(back.angles, geo.angles)
    with pytest.raises(GeometryError, match="dDetector"):
        Geometry.from_scanner_dict(dict(d, dDetector=[0.5, 0.6]), geo.angles)
    with pytest.raises(GeometryError, match="nVoxel"):
        Geometry.from_scanner_dict({k: v for k, v in d.items() if k != "nVoxel"}, geo.angles)


def test_circular_angles():
    np.testing.assert_allclose(circular_angles(4), [0, np.pi / 2, np.pi, 3 * np.pi / 2])
    np.testing.assert_allclose(circular_angles(3, np.pi, 0.1), [0.1, 0.1 + np.pi / 3,
                                                               0.1 + 2 * np.pi / 3])
    with pytest.raises(GeometryError, match="n_views"):
        circular_angles(0)


NAN = float("nan")
INVALID = [
    # (changes, field named in the message)
    (dict(DSO=7.0), "DSO"),                       # DSO >= DSD in cone mode
    (dict(DSO=8.0), "DSO"),
    (dict(DSD=0.0), "DSD"),
    (dict(DSD=-7.0), "DSD"),
    (dict(DSO=-1.0), "DSO"),
    (dict(sDetector=(0.0, 2.5)), "sDetector"),
    (dict(sDetector=(1.5, -2.5)), "sDetector"),
    (dict(sVoxel=(2.0, 0.0, 2.0)), "sVoxel"),
    (dict(nDetector=(0, 5)), "nDetector"),
    (dict(nDetector=(3, -5)), "nDetector"),
    (dict(nDetector=(3, 4.5)), "nDetector"),
    (dict(nVoxel=(4, 4, 0)), "nVoxel"),
    (dict(nVoxel=(4, 4.2, 4)), "nVoxel"),
    (dict(angles=()), "angles"),
    (dict(DSD=NAN), "DSD"),
    (dict(DSO=NAN), "DSO"),
    (dict(nDetector=(3, NAN)), "nDetector"),
    (dict(sDetector=(NAN, 2.5)), "sDetector"),
    (dict(nVoxel=(NAN, 4, 4)), "nVoxel"),
    (dict(sVoxel=(2.0, 2.0, NAN)), "sVoxel"),
    (dict(offOrigin=(0.0, NAN, 0.0)), "offOrigin"),
    (dict(offDetector=(NAN, 0.0)), "offDetector"),
    (dict(angles=(0.0, NAN)), "angles"),
    (dict(angles=(0.0, float("inf"))), "angles"),
    (dict(DSD=float("inf")), "DSD"),
    (dict(nDetector=(3,)), "nDetector"),
    (dict(sDetector=(1.5, 2.5, 1.0)), "sDetector"),
    (dict(nVoxel=(4, 4)), "nVoxel"),
    (dict(sVoxel=(2.0, 2.0)), "sVoxel"),
    (dict(offOrigin=(0.0, 0.0)), "offOrigin"),
    (dict(offDetector=(0.0, 0.0, 0.0)), "offDetector"),
    (dict(nDetector="abc"), "nDetector"),
    (dict(DSD="far"), "DSD"),
    (dict(mode="fan"), "mode"),
    (dict(sVoxel=(8.0, 8.0, 8.0)), "DSO"),        # source inside the volume
    (dict(offOrigin=(4.5, 0.0, 0.0)), "DSO"),     # shifted volume reaches the source
]


@pytest.mark.parametrize("changes,name", INVALID, ids=[f"{n}-{i}" for i, (_, n) in
                                                       enumerate(INVALID)])
def test_invalid_geometry_names_the_field(changes, name):
    args = dict(BASE, mode="cone", angles=(0.0, 1.0))
    args.update(changes)
    with pytest.raises(GeometryError, match=name):
        Geometry(**args)


def test_valid_edge_cases():
    # parallel beam has no source point, so DSO >= DSD is allowed there
    Geometry(**dict(BASE, mode="parallel", DSO=7.0, angles=[0.0]))
    # replace() validates again
    geo = _geo()
    with pytest.raises(GeometryError, match="DSO"):
        geo.replace(DSO=9.0)
    with pytest.raises(GeometryError, match="angles"):
        geo.with_angles([])
    # the stored angles are read-only
    with pytest.raises(ValueError):
        geo.angles[0] = 1.0
