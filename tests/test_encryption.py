"""Seed 001's transmission chain: resolution (3), quantizer (4)-(5), cipher (6)-(7), CRC, channel errors.

References are computed independently: exact rational arithmetic for the resolution
grid and the quantizer cells, Python integer polynomial division for the CRC, and
exhaustive enumeration of the error patterns for the CRC's miss rate.
"""
from __future__ import annotations

import os
from fractions import Fraction
from itertools import product

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from designer import InputError
from filters.encryption import (CRC4_ITU, Codec, crc, crc_ok, decrypt, encrypt, from_bits, key_stream, to_bits,
                                transmit)

# The same examples on every run (derandomized): a red CI is a real failure, reproduced by rerunning; set
# HYPOTHESIS_EXPLORE=1 to draw new ones (a search for counterexamples: how the one pinned below was found).
settings.register_profile("cfdesign-fixed", derandomize=True)
settings.register_profile("cfdesign-explore", derandomize=False)
settings.load_profile("cfdesign-explore" if os.environ.get("HYPOTHESIS_EXPLORE") else "cfdesign-fixed")

PAPER = Codec(0.2, 1.0, 8, 4.0)  # l_s = 0.2, omega = 1, K = 8, Lambda = 4 (Sec. IV)

bit_arrays = hnp.arrays(np.uint8, hnp.array_shapes(min_dims=1, max_dims=3, max_side=6), elements=st.integers(0, 1))


@given(data=st.data(), plain=bit_arrays)
def test_decrypting_the_ciphertext_returns_the_plaintext(data, plain):
    key = data.draw(hnp.arrays(np.uint8, plain.shape, elements=st.integers(0, 1)))
    cipher = encrypt(plain, key)
    np.testing.assert_array_equal(decrypt(cipher, key), plain)
    np.testing.assert_array_equal(cipher, (plain + key) % 2)  # XOR written as addition mod 2


@given(st.integers(1, 8), st.data())
def test_bits_are_k_minus_one_msb_first(L, data):
    k = data.draw(hnp.arrays(np.int64, st.integers(1, 20), elements=st.integers(1, 2**L)))
    b = to_bits(k, L)
    assert b.dtype == np.uint8 and b.shape == k.shape + (L,)
    assert [int("".join(map(str, row)), 2) + 1 for row in b] == k.tolist()
    np.testing.assert_array_equal(from_bits(b), k)
    np.testing.assert_array_equal(to_bits(np.array([6]), 3), [[1, 0, 1]])


def _exact_cell(zr: Fraction, omega: Fraction, K: int, lam: Fraction) -> int:
    """Quantizer (4) with half-open cells, in exact arithmetic, clipped to 1..K."""
    v = zr / omega
    for k in range(1, K + 1):
        if -lam + 2 * (k - 1) * lam / K <= v < -lam + 2 * k * lam / K:
            return k
    return K if v >= lam else 1


@pytest.mark.parametrize("l, om, lam, K", [("0.2", "1", 4, 8), ("0.1", "0.3", 4, 8), ("0.1", "0.3", 2, 16),
                                           ("0.7", "1", 5, 32), ("0.05", "1.7", 3, 64)])
def test_resolution_and_quantizer_match_exact_arithmetic(l, om, lam, K):
    """(3) then (4) at every resolution grid point n l, against exact rational arithmetic.

    Some grid points lie on cell boundaries; in floating point they can land just below
    one (-6 * 0.1 = -0.6000000000000001 on the boundary -0.6 of the second setting).
    """
    c = Codec(float(l), float(om), K, float(lam))
    le, ome = Fraction(l), Fraction(om)
    top = int(ome * lam / le) + 2
    for n in range(-top, top + 1):
        z = float((n + Fraction(1, 2) if n > 0 else n - Fraction(1, 2) if n < 0 else 0) * le)  # inside n's preimage
        zr = c.resolve(np.array(z))
        assert zr == pytest.approx(float(n * le), abs=1e-12)
        assert c.index(zr) == _exact_cell(n * le, ome, K, Fraction(lam)), (n, float(zr))
    for z in (0.59, 0.61, -0.61, 0.19, -0.19, 0.2, -0.2, 3.99, -3.99):  # (3) on the stored binary values
        q = Fraction(z) / Fraction(0.2)
        exact = (q.__floor__() if z >= 0.2 else q.__ceil__() if z <= -0.2 else 0) * Fraction(0.2)
        assert PAPER.resolve(np.array(z)) == pytest.approx(float(exact), abs=1e-15), z


resolutions = st.floats(0.01, 1.0)
scales = st.floats(0.1, 10.0)
levels = st.sampled_from([2, 4, 8, 16, 64])


@given(st.floats(-1.0, 1.0), resolutions, scales, levels, st.floats(0.5, 8.0))
@example(-5.9099669278051e-10, 1.0, 1.0, 2, 1.0)  # 6e-10 cell widths below a boundary: the upper cell (found by CI)
def test_quantization_error_bound_5(u, l, om, K, lam):
    """(5), |zr - ω U| <= ω Λ / K, up to the module's documented cell tolerance: a value within 1e-9 cell widths
    (2 ω Λ / K) below a boundary goes to the upper cell, so the bound holds within a factor 1 + 2e-9."""
    c = Codec(l, om, K, lam)
    zr = u * om * lam  # |zr / omega| <= Lambda: inside the range
    k = c.index(zr)
    assert 1 <= k <= K
    assert abs(zr - c.reconstruct(k)) <= om * lam / K * (1 + 2e-9) + 1e-15 * om * lam


@given(st.floats(-0.999, 0.999), resolutions, scales, levels, st.floats(0.5, 8.0))
def test_resolution_plus_quantization_error_bound_12(u, l, om, K, lam):
    c = Codec(l, om, K, lam)
    z = u * om * lam
    zr = c.resolve(z)
    assert abs(z - zr) < l and abs(zr) <= abs(z) and np.sign(zr) in (0, np.sign(z))
    assert abs(zr / l - round(zr / l)) < 1e-9  # on the resolution grid
    assert abs(z - c.reconstruct(c.index(zr))) < c.bound


def test_saturation_is_sent_as_the_extreme_cell():
    zr = np.array([-9.0, -4.0, 3.999, 4.0, 12.0])
    np.testing.assert_array_equal(PAPER.index(zr), [1, 1, 8, 8, 8])
    np.testing.assert_array_equal(PAPER.saturated(zr), [True, True, False, True, True])


def _crc_reference(payload: list[int], poly: int) -> list[int]:
    """Remainder of m(x) x^r modulo poly by Python integer long division."""
    r = poly.bit_length() - 1
    m = int("".join(map(str, payload)), 2) << r
    for shift in range(m.bit_length() - 1, r - 1, -1):
        if m >> shift & 1:
            m ^= poly << (shift - r)
    return [(m >> (r - 1 - i)) & 1 for i in range(r)]


@settings(max_examples=60)
@given(st.lists(st.integers(0, 1), min_size=1, max_size=24), st.sampled_from([CRC4_ITU, 0b111, 0x107]))
def test_crc_is_the_polynomial_remainder(payload, poly):
    assert crc(np.array(payload), poly).tolist() == _crc_reference(payload, poly)


@given(st.lists(st.integers(0, 1), min_size=1, max_size=11), st.data())
def test_crc_detects_every_single_bit_error(payload, data):
    """Any flipped bit of the codeword (payload or check bits) fails the check; CRC-4 also catches double errors."""
    b = np.array(payload, dtype=np.uint8)
    word = np.concatenate([b, crc(b)])
    n = word.size
    assert crc_ok(word[:b.size], word[b.size:])
    i = data.draw(st.integers(0, n - 1))
    bad = word.copy()
    bad[i] ^= 1
    assert not crc_ok(bad[:b.size], bad[b.size:])
    j = data.draw(st.integers(0, n - 1).filter(lambda j: j != i))
    bad[j] ^= 1  # codeword of at most 15 bits: x^4 + x + 1 is primitive of period 15
    assert not crc_ok(bad[:b.size], bad[b.size:])


def _pass_probability(L: int, p: float) -> tuple[float, float]:
    """P(no bit error) and P(an error pattern the CRC misses), by enumerating all patterns (linearity of the CRC)."""
    clean = (1 - p) ** (L + 4)
    missed = 0.0
    for e in product((0, 1), repeat=L + 4):
        if any(e) and _crc_reference(list(e[:L]), CRC4_ITU) == list(e[L:]):
            w = sum(e)
            missed += p**w * (1 - p) ** (L + 4 - w)
    return clean, missed


def test_transmission_without_errors_is_the_quantized_value():
    rng = np.random.default_rng(0)
    z = rng.uniform(-4, 4, size=(30, 120, 2))
    tx = transmit(z, PAPER, rng)
    assert tx.available.all() and not tx.detected.any() and not tx.undetected.any()
    assert tx.key.shape == tx.plaintext.shape == tx.ciphertext.shape == (30, 120, 2, 3)
    np.testing.assert_array_equal(tx.decrypted_bits, tx.plaintext)
    np.testing.assert_array_equal(tx.decrypted, PAPER.reconstruct(PAPER.index(PAPER.resolve(z))))
    assert abs(tx.key.mean() - 0.5) < 5 * np.sqrt(0.25 / tx.key.size)
    # the one-time pad hides the plaintext: a ciphertext bit is independent of the plaintext bit
    assert abs(tx.ciphertext[tx.plaintext == 1].mean() - 0.5) < 0.02
    assert np.all(np.abs(z - tx.decrypted) < PAPER.bound)


def test_channel_errors_crc_and_dropouts_frequencies():
    rng = np.random.default_rng(1)
    pe, pd = 0.05, 0.1
    z = rng.uniform(-3.9, 3.9, size=(200_000, 2))
    tx = transmit(z, PAPER, rng, bit_error_prob=pe, dropout_prob=pd)
    n = z.size
    clean, missed = _pass_probability(3, pe)
    for observed, p in ((tx.dropped.mean(), pd), (tx.available.mean(), (1 - pd) * (clean + missed)),
                        (tx.undetected.mean(), (1 - pd) * missed),
                        (tx.detected.mean(), (1 - pd) * (1 - clean - missed))):
        assert abs(observed - p) < 5 * np.sqrt(p * (1 - p) / n) + 1e-12, (observed, p)
    assert np.isnan(tx.decrypted[~tx.available]).all()
    ok = tx.available & ~tx.undetected
    np.testing.assert_array_equal(tx.decrypted[ok], PAPER.reconstruct(tx.index[ok]))
    single = (tx.received ^ np.concatenate([tx.ciphertext, tx.checksum], -1)).sum(-1) == 1
    assert single.any() and not tx.available[single & ~tx.dropped].any()


def test_a_seed_reproduces_the_transmission_and_a_given_key_is_used():
    z = np.random.default_rng(2).normal(size=(50, 2))
    a = transmit(z, PAPER, np.random.default_rng(3), bit_error_prob=0.1, dropout_prob=0.2)
    b = transmit(z, PAPER, np.random.default_rng(3), bit_error_prob=0.1, dropout_prob=0.2)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    key = key_stream(np.random.default_rng(4), z.shape, 3)
    c = transmit(z, PAPER, np.random.default_rng(5), key=key)
    np.testing.assert_array_equal(c.key, key)
    np.testing.assert_array_equal(c.ciphertext, c.plaintext ^ key)


def test_per_sensor_settings():
    c = Codec([0.2, 0.5], [1.0, 2.0], 8, 4.0)
    np.testing.assert_allclose(c.bound, [0.7, 1.5])
    z = np.array([[0.45, 0.45], [-7.9, 7.9]])
    np.testing.assert_allclose(c.resolve(z), [[0.4, 0.0], [-7.8, 7.5]])
    np.testing.assert_array_equal(c.index(c.resolve(z)), [[5, 5], [1, 8]])


@pytest.mark.parametrize("call, name", [
    (lambda: Codec(0.0, 1.0, 8, 4.0), "resolution"),
    (lambda: Codec(0.2, -1.0, 8, 4.0), "quant_scale"),
    (lambda: Codec(0.2, 1.0, 6, 4.0), "quant_levels"),
    (lambda: Codec(0.2, 1.0, 8, np.nan), "quant_range"),
    (lambda: transmit(np.zeros((3, 2)), PAPER, np.random.default_rng(0), bit_error_prob=1.5), "bit_error_prob"),
    (lambda: transmit(np.zeros((3, 2)), PAPER, np.random.default_rng(0), dropout_prob=-0.1), "dropout_prob"),
    (lambda: transmit(np.zeros((3, 2)), PAPER, np.random.default_rng(0), poly=0b1000), "poly"),
    (lambda: transmit(np.zeros((3, 2)), PAPER, np.random.default_rng(0), key=np.zeros((3, 2, 2), int)), "key"),
    (lambda: transmit(np.zeros((3, 2)), PAPER, "rng"), "rng"),
    (lambda: transmit(np.array([np.nan, 0.0]), PAPER, np.random.default_rng(0)), "z"),
    (lambda: transmit(np.zeros((3, 2)), Codec([0.2, 0.2, 0.2], 1.0, 8, 4.0), np.random.default_rng(0)),
     "resolution"),
    (lambda: encrypt(np.array([0, 2]), np.array([0, 1])), "plaintext"),
    (lambda: to_bits(np.array([9]), 3), "k"),
    (lambda: PAPER.reconstruct(np.array([0])), "k"),
])
def test_bad_inputs_name_the_parameter(call, name):
    with pytest.raises(InputError, match=name):
        call()
