"""designer.fileio.write_npz: the .npz files of designs and studies."""
from __future__ import annotations

import numpy as np

from designer.fileio import write_npz


def test_write_npz_is_what_numpy_reads_back(tmp_path):
    """designer.fileio.write_npz (zlib at its fastest level): np.load gives the same arrays, dtypes and shapes, a
    non-contiguous view and an empty array included."""
    rng = np.random.default_rng(3)
    arrays = {"Phi": rng.normal(size=(4, 3, 5, 5)).swapaxes(0, 1), "C": np.zeros((3, 4, 5, 5)),
              "valid": rng.random((3, 4)) < 0.5, "steps": np.array(7), "none": np.zeros((0, 2))}
    write_npz(tmp_path / "a.npz", **arrays)
    with np.load(tmp_path / "a.npz", allow_pickle=False) as got:
        assert sorted(got.files) == sorted(arrays)
        for name, value in arrays.items():
            assert got[name].dtype == value.dtype and got[name].shape == value.shape
            np.testing.assert_array_equal(got[name], value)
