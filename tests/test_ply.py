"""3DGS-style PLY: round trip, header as viewers read it, byte layout by hand."""
import struct

import numpy as np
import pytest

import mi_grg  # noqa: F401  (sets up LLVM before mitsuba)
from mi_grg.core.gaussians import Gaussians
from mi_grg.data.ply import OPACITY_FLOOR, PlyError, SH_C0, load_ply, save_ply

VIEWER_ORDER = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def random_gaussians(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rho = rng.uniform(0.0, 3.0, n)
    rho[0] = 0.0
    rho[1] = 1e-30   # below the opacity floor
    return Gaussians.from_numpy(rng.normal(size=(n, 3)), np.exp(rng.uniform(-6, 1, (n, 3))),
                                q, rho)


def split_header(raw: bytes):
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines(), raw[end:]


def test_round_trip(tmp_path, rng):
    g = random_gaussians(rng, 200)
    path = save_ply(g, tmp_path / "g.ply")
    back = load_ply(path)
    a, b = g.numpy(), back.numpy()
    np.testing.assert_array_equal(b["positions"], a["positions"])
    np.testing.assert_allclose(b["scales"], a["scales"], rtol=1e-6, atol=0)
    np.testing.assert_allclose(b["rotations"], a["rotations"], rtol=0, atol=2 ** -23)
    expect = a["densities"].copy()
    expect[1] = 0.0   # under exp(-60): stored at the floor, read back as 0
    np.testing.assert_allclose(b["densities"], expect, rtol=1e-6, atol=0)
    assert b["densities"][0] == 0.0


def test_header_is_what_3dgs_viewers_read(tmp_path, rng):
    g = random_gaussians(rng, 7)
    lines, body = split_header((save_ply(g, tmp_path / "g.ply")).read_bytes())
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    assert lines[-1] == "end_header"
    content = [ln for ln in lines if not ln.startswith("comment")]
    assert content[2] == "element vertex 7"
    assert content[3:-1] == [f"property float {k}" for k in VIEWER_ORDER]
    assert len(body) == 7 * 4 * len(VIEWER_ORDER)
    # decode as a viewer does: sigmoid(opacity), exp(scale), normalised rot, SH DC colour
    rec = np.frombuffer(body, dtype=np.dtype([(k, "<f4") for k in VIEWER_ORDER]))
    a = g.numpy()
    rho = a["densities"].astype(np.float64)
    alpha = 1 / (1 + np.exp(-rec["opacity"].astype(np.float64)))
    np.testing.assert_allclose(alpha, rho / (1 + rho), rtol=1e-6, atol=1e-20)
    scales = np.exp(np.stack([rec[f"scale_{k}"] for k in range(3)], -1).astype(np.float64))
    np.testing.assert_allclose(scales, a["scales"], rtol=1e-6)
    q = np.stack([rec[f"rot_{k}"] for k in range(4)], -1)
    np.testing.assert_allclose(q / np.linalg.norm(q, axis=1, keepdims=True), a["rotations"],
                               atol=1e-6)
    colour = 0.5 + SH_C0 * np.stack([rec[f"f_dc_{k}"] for k in range(3)], -1)
    np.testing.assert_allclose(colour, np.repeat((rho / rho.max())[:, None], 3, 1), atol=1e-6)
    assert not np.any(np.stack([rec[k] for k in ("nx", "ny", "nz")]))


def test_byte_layout_by_hand(tmp_path):
    """One Gaussian, the 17 little-endian float32 values written out by hand."""
    g = Gaussians.from_numpy([[0.5, -1.25, 2.0]], [[0.5, 2.0, 0.25]], [[1.0, 0.0, 0.0, 0.0]],
                             [2.0])
    _, body = split_header(save_ply(g, tmp_path / "one.ply").read_bytes())
    f_dc = (1.0 - 0.5) / SH_C0   # the only Gaussian is the brightest: grey 1
    expected = struct.pack("<17f", 0.5, -1.25, 2.0, 0, 0, 0, f_dc, f_dc, f_dc,
                           np.log(2.0),                          # log(density)
                           np.log(0.5), np.log(2.0), np.log(0.25),
                           1.0, 0.0, 0.0, 0.0)
    assert body == expected


def test_sh_rest_adds_45_zero_coefficients(tmp_path, rng):
    g = random_gaussians(rng, 3)
    path = save_ply(g, tmp_path / "sh.ply", sh_rest=True)
    lines, body = split_header(path.read_bytes())
    props = [ln.split()[-1] for ln in lines if ln.startswith("property")]
    assert props[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert len(body) == 3 * 4 * 62
    np.testing.assert_allclose(load_ply(path).numpy()["scales"], g.numpy()["scales"], rtol=1e-6)


def test_reads_3dgs_files_with_unnormalised_rotations_and_extra_properties(tmp_path, rng):
    """A file as 3DGS writes it (raw quaternions, f_rest_*, double precision here)."""
    names = VIEWER_ORDER[:9] + [f"f_rest_{i}" for i in range(45)] + VIEWER_ORDER[9:]
    n = 5
    rec = np.zeros(n, dtype=np.dtype([(k, "<f8") for k in names]))
    pos = rng.normal(size=(n, 3))
    q = rng.normal(size=(n, 4)) * 3.0
    logit = rng.normal(size=n)
    for k, a in enumerate("xyz"):
        rec[a] = pos[:, k]
        rec[f"scale_{k}"] = -3.0 + k
    for k in range(4):
        rec[f"rot_{k}"] = q[:, k]
    rec["opacity"] = logit
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 5\n" + "".join(
        f"property double {k}\n" for k in names) + "end_header\n"
    path = tmp_path / "3dgs.ply"
    path.write_bytes(header.encode() + rec.tobytes())
    g = load_ply(path).numpy()
    np.testing.assert_allclose(g["positions"], pos, rtol=1e-6)
    np.testing.assert_allclose(g["rotations"], q / np.linalg.norm(q, axis=1, keepdims=True),
                               atol=1e-6)
    np.testing.assert_allclose(g["scales"], np.exp([[-3.0, -2.0, -1.0]] * n), rtol=1e-6)
    alpha = 1 / (1 + np.exp(-logit))
    np.testing.assert_allclose(g["densities"], alpha / (1 - alpha), rtol=1e-5)


def test_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(PlyError, match="not a PLY"):
        load_ply(bad)
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(PlyError, match="binary"):
        load_ply(bad)
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\n"
                    b"property float x\nend_header\n")
    with pytest.raises(PlyError, match="lacks"):
        load_ply(bad)
    names = VIEWER_ORDER
    bad.write_bytes(("ply\nformat binary_little_endian 1.0\nelement vertex 2\n" + "".join(
        f"property float {k}\n" for k in names) + "end_header\n").encode() + b"\0" * 10)
    with pytest.raises(PlyError, match="expected 2 vertices"):
        load_ply(bad)


def test_empty_and_floor(tmp_path):
    g = Gaussians.from_numpy(np.zeros((0, 3)), np.zeros((0, 3)))
    back = load_ply(save_ply(g, tmp_path / "empty.ply"))
    assert len(back) == 0
    one = Gaussians.from_numpy([[0, 0, 0]], [[1, 1, 1]], None, [0.0])
    _, body = split_header(save_ply(one, tmp_path / "zero.ply").read_bytes())
    assert struct.unpack("<17f", body)[9] == OPACITY_FLOOR
