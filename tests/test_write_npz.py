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


def test_a_large_array_is_written_in_pieces_with_progress_lines_and_the_same_bytes(tmp_path, monkeypatch, capsys):
    """An array above ``NPZ_PIECE`` bytes is written a piece at a time, a progress line due between pieces (the
    megabytes written of the file's), and its member holds the bytes numpy's own ``write_array`` writes; a Fortran
    ordered array keeps numpy's path (its header says so)."""
    import io
    import zipfile

    from designer import fileio, progress

    monkeypatch.setattr(fileio, "NPZ_PIECE", 1 << 20)
    monkeypatch.setattr(progress, "FIRST_S", 0.0)
    monkeypatch.setattr(progress, "EVERY_S", 0.0)
    rng = np.random.default_rng(5)
    arrays = {"big": rng.normal(size=(3, 128, 1024)), "odd": rng.normal(size=(5, 7777)),
              "fortran": np.asfortranarray(rng.normal(size=(300, 900))), "small": np.arange(5)}
    with progress.showing():
        write_npz(tmp_path / "a.npz", **arrays)
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "MB written" in ln]
    total = sum(a.nbytes for a in arrays.values()) >> 20
    assert [ln.split("MB written ")[1].split(",")[0].split(" ")[0] for ln in lines[:3]] == \
        [f"{k}/{total}" for k in (1, 2, 3)], lines
    assert lines[-1].split("MB written ")[1].startswith(f"{total}/{total}")
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        for name, value in arrays.items():
            ref = io.BytesIO()
            np.lib.format.write_array(ref, value, allow_pickle=False)
            assert zf.read(f"{name}.npy") == ref.getvalue(), name
