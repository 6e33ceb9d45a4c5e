"""NAF / SAX-NeRF pickles as their own tools write them (``pickle.HIGHEST_PROTOCOL``, and
protocols 2 to 4, numpy 1 and numpy 2 module names) load; a hostile payload is refused
before it runs."""
from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from mi_grg.core.geometry import circular_angles
from mi_grg.data.dataset import DatasetError, load_case
from mi_grg.data.naf import load_naf
from mi_grg.data.raw_import import import_scan

N_DET, N_VOX = 16, 8


def naf_dict():
    """A small pickle's content, laid out as NAF's generator writes it."""
    rng = np.random.default_rng(0)
    tr, va = circular_angles(8), circular_angles(4) + 0.1
    return {"DSD": 1500.0, "DSO": 1000.0, "nDetector": [N_DET, N_DET], "dDetector": [1.0, 1.0],
            "nVoxel": [N_VOX] * 3, "dVoxel": [1.0] * 3, "offOrigin": [0, 0, 0],
            "offDetector": [0, 0], "totalAngle": 360.0, "startAngle": 0.0, "accuracy": 0.5,
            "mode": "cone", "filter": None, "numTrain": 8, "numVal": 4,
            "train": {"projections": rng.random((8, N_DET, N_DET)).astype(np.float32),
                      "angles": tr},
            "val": {"projections": rng.random((4, N_DET, N_DET)).astype(np.float32),
                    "angles": va},
            "image": rng.random((N_VOX,) * 3).astype(np.float32),
            "scalars": [np.float64(1.5), np.int64(3), 2.5, "mm"]}


def numpy1_names(blob: bytes) -> bytes:
    """Protocol 2 names classes in text (GLOBAL opcodes): respell numpy 2's module names
    as numpy 1 (the one NAF's environment had) wrote them."""
    assert b"numpy._core" in blob
    return blob.replace(b"numpy._core.", b"numpy.core.")


PICKLES = {f"protocol {p}": (lambda d, p=p: pickle.dumps(d, protocol=p)) for p in (2, 3, 4, 5)}
PICKLES["protocol 2, numpy 1 names"] = lambda d: numpy1_names(pickle.dumps(d, protocol=2))


@pytest.mark.parametrize("kind", sorted(PICKLES))
def test_naf_pickle_of_every_protocol_loads(kind, tmp_path):
    data = naf_dict()
    path = tmp_path / "scan.pickle"
    path.write_bytes(PICKLES[kind](data))
    loaded = load_naf(path)
    for split in ("train", "val"):
        np.testing.assert_array_equal(loaded[split]["projections"], data[split]["projections"])
        np.testing.assert_array_equal(loaded[split]["angles"], data[split]["angles"])
    np.testing.assert_array_equal(loaded["image"], data["image"])
    assert loaded["scalars"] == data["scalars"] and loaded["filter"] is None


def test_highest_protocol_pickle_imports(tmp_path):
    """NAF's and R2-Gaussian's scripts: pickle.dump(data, f, pickle.HIGHEST_PROTOCOL)."""
    data = naf_dict()
    path = tmp_path / "scan.pickle"
    with open(path, "wb") as f:
        pickle.dump(data, f, pickle.HIGHEST_PROTOCOL)
    rec = import_scan(path, tmp_path / "case")
    case = load_case(tmp_path / "case", rescale=False)
    assert rec["source"]["kind"] == "naf-pickle"
    np.testing.assert_array_equal(case.train, data["train"]["projections"])
    np.testing.assert_array_equal(case.vol_gt, data["image"])


class _System:
    """Unpickles as os.system(command)."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


class _Codec:
    """Unpickles as _codecs.encode(text, encoding): a codec other than protocol 2's."""

    def __reduce__(self):
        import _codecs
        return _codecs.encode, ("x", "rot13")


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_hostile_pickle_is_refused_without_running(protocol, tmp_path):
    marker = tmp_path / "owned"
    data = naf_dict()
    for where in ("top", "nested", "codec"):
        payload = _Codec() if where == "codec" else _System(f"echo owned > {marker}")
        bad = {**data, "x": payload} if where == "top" else \
            {**data, "train": {**data["train"], "angles": [payload]}}
        path = tmp_path / f"evil_{where}.pickle"
        path.write_bytes(pickle.dumps(bad, protocol=protocol))
        assert b"system" in path.read_bytes() or where == "codec"
        with pytest.raises(DatasetError, match="refuses"):
            load_naf(path)
        assert not marker.exists(), where   # refused before it ran


def test_object_arrays_are_refused(tmp_path):
    path = tmp_path / "objs.pickle"
    path.write_bytes(pickle.dumps({**naf_dict(), "x": np.array([{}], dtype=object)},
                                  protocol=5))
    with pytest.raises(DatasetError, match="refuses the type builtins.dict|object"):
        load_naf(path)
