"""The fused kernels' random streams (filters.fused.streams) against NumPy's own Generator.

Reference: ``numpy.random.Generator`` itself (``standard_normal``, ``random``, its state
afterwards), for every bit generator NumPy ships; a stream must give the same numbers bit
for bit, in the same order, and leave the Generator where NumPy's draws would.
"""
from __future__ import annotations

import numba
import numpy as np
import pytest

from filters.fused import streams as S

BIT_GENERATORS = [np.random.PCG64, np.random.PCG64DXSM, np.random.MT19937, np.random.Philox, np.random.SFC64]


@numba.njit
def _mixed(st, normals, uniforms, pattern):
    """Draw through the kernels' own path (load / normal / uniform / keep): ``pattern[i]`` normals then one
    uniform, over and over."""
    S_, h, lo = S.load(st)
    iz = iu = 0
    for p in pattern:
        for _ in range(p):
            z, h, lo = S.normal(S_, h, lo)
            normals[iz] = z
            iz += 1
        u, h, lo = S.uniform(S_, h, lo)
        uniforms[iu] = u
        iu += 1
    S.keep(st, h, lo)


@pytest.mark.parametrize("bit_generator", BIT_GENERATORS, ids=lambda b: b.__name__)
def test_a_stream_draws_numpys_numbers_and_leaves_the_generator_where_numpy_would(bit_generator):
    ours, ref = np.random.Generator(bit_generator(2024)), np.random.Generator(bit_generator(2024))
    st = S.open_stream(ours)
    big = np.empty(400_000)  # about 5000 draws take the ziggurat's slow paths, some its tail
    S.draw_normals(st, big, 0, 1000)
    S.draw_normals(st, big, 1000, big.size - 1000)
    u1 = S.draw_uniform(st)
    us = np.empty(333)
    S.draw_uniforms(st, us, 0, us.size)
    pattern = np.random.default_rng(5).integers(0, 9, 200)
    zs, uu = np.empty(pattern.sum()), np.empty(pattern.size)
    _mixed(st, zs, uu, pattern)
    S.close_stream(ours, st)

    assert np.array_equal(big, ref.standard_normal(big.size))
    assert u1 == ref.random()
    assert np.array_equal(us, ref.random(us.size))
    for p, u, i in zip(pattern, uu, np.concatenate([[0], np.cumsum(pattern)])):
        assert np.array_equal(zs[i:i + p], ref.standard_normal(p))
        assert u == ref.random()
    # the Generator goes on as NumPy's: its state, and a 32-bit draw (NumPy's buffered half-word) after it
    assert np.array_equal(ours.random(5), ref.random(5))
    assert np.array_equal(ours.integers(0, 2**31, 7, dtype=np.int32), ref.integers(0, 2**31, 7, dtype=np.int32))
    assert np.array_equal(ours.standard_normal(3), ref.standard_normal(3))


def test_the_tail_of_the_ziggurat_is_exercised():
    """The tail branch (layer 0, beyond r = 3.654) is about 1 in 4000 draws: the comparison above covers it."""
    z = np.empty(400_000)
    st = S.open_stream(np.random.default_rng(2024))
    S.draw_normals(st, z, 0, z.size)
    assert (np.abs(z) > S.NOR_R).sum() >= 20


def test_a_pcg64_generators_half_word_buffer_survives_the_stream():
    """NumPy's PCG64 keeps half of a 64-bit output for its next 32-bit draw; the stream's draws (64-bit) leave it."""
    ours, ref = np.random.default_rng(7), np.random.default_rng(7)
    for g in (ours, ref):
        g.integers(0, 2**31, 1, dtype=np.int32)  # now has a buffered 32-bit half
    assert ours.bit_generator.state["has_uint32"] == 1
    st = S.open_stream(ours)
    z = np.empty(10)
    S.draw_normals(st, z, 0, 10)
    S.close_stream(ours, st)
    assert np.array_equal(z, ref.standard_normal(10))
    assert ours.bit_generator.state == ref.bit_generator.state
