"""Seed 001's transmission chain: sensor resolution, uniform quantizer, XOR cipher, CRC, channel errors.

For a measurement ``z`` of sensor ``s`` (Song, Wang, Li, Sec. II)::

    zr     = l_s trunc(z / l_s)                          resolution (3): rounds toward zero
    k      = cell of zr / ω_s in the uniform quantizer   (4): K = 2^L cells of width 2Λ/K on [-Λ, Λ)
    B      = k - 1 written in L bits, MSB first          the plaintext
    B̄      = XOR(B, E)                                  encryption (6) with the key stream E
    B̃      = XOR(B̄, E) = B                              decryption (7)
    z̃      = ω_s U(zr / ω_s) = ω_s (-Λ + (2k - 1) Λ / K) the decrypted (reconstructed) value

so that ``|zr - z̃| <= ω_s Λ / K`` (5) inside the range and ``|z - z̃| < L̄_s = ω_s Λ / K + l_s`` (12).

Conventions where the paper is silent (G4, G5 of the extraction notes):

* quantizer cells are half-open ``[lo, hi)``; the index is clipped to ``1..K``, so a
  saturated input (``|zr / ω| >= Λ``, where (4) outputs ``±Λ``, which no L-bit
  codeword represents) is sent as the extreme cell.  The cell is computed with a
  tolerance of ``1e-9`` cell widths so that resolution grid points lying on a cell
  boundary fall in the cell the half-open convention assigns to the exact value
  (with l = 0.1, ω = 0.3, Λ = 4, K = 8 the grid point ``-6 · 0.1`` is
  ``-0.6000000000000001`` in floating point, just below the boundary ``-0.6``);
* the key stream is i.i.d. Bernoulli(1/2) bits per sensor and step (a one-time pad),
  drawn from the Generator passed in;
* error detection (Remark 1): a CRC of the *ciphertext* is appended (a CRC of the
  plaintext would reveal it: 16 codewords of 7 bits for 8 plaintexts).  The default
  generator is CRC-4-ITU, ``x^4 + x + 1`` (``0b10011``), zero initial register, no
  reflection, no final XOR.  Being primitive of period 15, it detects every single-
  and double-bit error in codewords of up to 15 bits (here L + 4 = 7).  A packet
  whose CRC fails is discarded: the measurement is unavailable (α_s = 0, Remark 2);
  an error pattern that the CRC misses delivers a wrong value as available (recorded
  in ``Transmission.undetected``);
* packet dropouts (Remark 2) are independent Bernoulli events per sensor and step.

All functions are batched over leading dimensions (``z`` has shape ``(..., N)``,
sensors last) and draw only from the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from designer.validation import InputError, check_int, check_positive, check_probability, check_rng

__all__ = [
    "CRC4_ITU", "Codec", "EncryptedChannel", "to_bits", "from_bits", "key_stream", "encrypt", "decrypt", "crc",
    "crc_ok", "Transmission", "transmit", "transmit_runs",
]

CRC4_ITU = 0b10011  # x^4 + x + 1 (ITU-T G.704)
_CELL_TOL = 1e-9  # in cell widths, see the module notes


@dataclass(frozen=True, eq=False)
class Codec:
    """Resolution and quantizer settings of every sensor: ``l_s`` (3), ``ω_s``, ``K``, ``Λ`` (4).

    ``resolution`` and ``quant_scale`` are scalars or arrays that broadcast against the
    measurements ``(..., N)`` (one value per sensor, or per step and sensor).
    """

    resolution: np.ndarray
    quant_scale: np.ndarray
    quant_levels: int
    quant_range: float

    def __post_init__(self):
        object.__setattr__(self, "resolution", check_positive("resolution", self.resolution))
        object.__setattr__(self, "quant_scale", check_positive("quant_scale", self.quant_scale))
        levels = check_int("quant_levels", self.quant_levels, 2)
        if levels & (levels - 1):
            raise InputError(f"quant_levels must be a power of two (K = 2^L), got {levels}")
        object.__setattr__(self, "quant_levels", levels)
        lam = check_positive("quant_range", self.quant_range)
        if lam.ndim:
            raise InputError(f"quant_range must be a scalar, got shape {lam.shape}")
        object.__setattr__(self, "quant_range", float(lam))

    @property
    def bits(self) -> int:
        """Codeword length ``L = log2 K``."""
        return self.quant_levels.bit_length() - 1

    @property
    def bound(self) -> np.ndarray:
        """``L̄_s = ω_s Λ / K + l_s`` of (12)."""
        return self.quant_scale * self.quant_range / self.quant_levels + self.resolution

    def resolve(self, z) -> np.ndarray:
        """Resolution (3): ``l trunc(z / l)``, i.e. floor for z >= l, 0 in (-l, l), ceil for z <= -l."""
        z = np.asarray(z, dtype=float)
        zr = self.resolution * np.trunc(z / self.resolution)
        # z / l can round up onto the next grid point (6.6 / 0.04 -> 165.0, 165 * 0.04 = 6.6000000000000005):
        # never let rounding push |zr| past |z|; + 0.0: no negative zeros
        return np.copysign(np.minimum(np.abs(zr), np.abs(z)), z) + 0.0

    def index(self, zr) -> np.ndarray:
        """Quantizer cell ``k`` in 1..K of ``zr / ω`` (4), half-open cells, clipped at saturation."""
        lam = np.asarray(zr, dtype=float) / self.quant_scale
        u = (lam + self.quant_range) * (self.quant_levels / (2.0 * self.quant_range))
        return np.clip(np.floor(u + _CELL_TOL).astype(np.int64) + 1, 1, self.quant_levels)

    def saturated(self, zr) -> np.ndarray:
        """Inputs outside the quantizer's range (``|zr / ω| >= Λ``), where (4) saturates."""
        return np.abs(np.asarray(zr, dtype=float) / self.quant_scale) >= self.quant_range

    def reconstruct(self, k) -> np.ndarray:
        """``ω U = ω (-Λ + (2k - 1) Λ / K)`` for cells ``k`` in 1..K."""
        k = np.asarray(k)
        if np.any((k < 1) | (k > self.quant_levels)):
            raise InputError(f"k must hold quantizer cells in 1..{self.quant_levels}")
        lam = self.quant_range
        return self.quant_scale * (-lam + (2 * k - 1) * lam / self.quant_levels)


def _bits(name: str, bits) -> np.ndarray:
    b = np.asarray(bits)
    if b.ndim < 1 or not (np.issubdtype(b.dtype, np.integer) or b.dtype == bool) or np.any((b != 0) & (b != 1)):
        raise InputError(f"{name} must be an array (..., L) of 0/1 bits")
    return b.astype(np.uint8)


def to_bits(k, bits: int) -> np.ndarray:
    """Plaintext of cells ``k`` in 1..2^bits: ``k - 1`` in ``bits`` bits, MSB first, uint8 (..., bits)."""
    bits = check_int("bits", bits, 1)
    k = np.asarray(k)
    if not np.issubdtype(k.dtype, np.integer) or np.any((k < 1) | (k > 2**bits)):
        raise InputError(f"k must hold integers in 1..{2**bits}")
    shifts = np.arange(bits - 1, -1, -1)
    return (((k[..., None] - 1) >> shifts) & 1).astype(np.uint8)


def from_bits(bits) -> np.ndarray:
    """Cells ``k = 1 + (bits read MSB first)``, the inverse of :func:`to_bits`."""
    b = _bits("bits", bits).astype(np.int64)
    return (b << np.arange(b.shape[-1] - 1, -1, -1)).sum(axis=-1) + 1


def key_stream(rng: np.random.Generator, shape, bits: int) -> np.ndarray:
    """Pre-generated key ``E_s(t)``: i.i.d. Bernoulli(1/2) bits of shape ``shape + (bits,)``, e.g. (T, N, L)."""
    check_rng(rng)
    bits = check_int("bits", bits, 1)
    return rng.integers(0, 2, size=tuple(shape) + (bits,), dtype=np.uint8)


def encrypt(plaintext, key) -> np.ndarray:
    """Ciphertext (6): ``XOR(B, E)`` bit by bit."""
    p, e = _bits("plaintext", plaintext), _bits("key", key)
    if p.shape != e.shape:
        raise InputError(f"key must have the plaintext's shape {p.shape}, got {e.shape}")
    return p ^ e


def decrypt(ciphertext, key) -> np.ndarray:
    """Decrypted bits (7): ``XOR(B̄, E)``."""
    c, e = _bits("ciphertext", ciphertext), _bits("key", key)
    if c.shape != e.shape:
        raise InputError(f"key must have the ciphertext's shape {c.shape}, got {e.shape}")
    return c ^ e


def _generator(poly: int) -> np.ndarray:
    if isinstance(poly, bool) or not isinstance(poly, (int, np.integer)) or poly < 3 or not poly & 1:
        raise InputError(f"poly must be a CRC generator polynomial (an odd integer >= 3, e.g. 0b10011), got {poly!r}")
    r = int(poly).bit_length() - 1
    return np.array([(int(poly) >> (r - 1 - i)) & 1 for i in range(r)], dtype=np.uint8)  # x^(r-1) .. x^0


def crc(bits, poly: int = CRC4_ITU) -> np.ndarray:
    """CRC of ``bits`` (..., n): the remainder of ``m(x) x^r`` modulo ``poly`` (degree r), r bits MSB first."""
    b = _bits("bits", bits)
    taps = _generator(poly)
    reg = np.zeros(b.shape[:-1] + taps.shape, dtype=np.uint8)
    for i in range(b.shape[-1]):  # one shift of the division register per message bit
        feedback = reg[..., 0] ^ b[..., i]
        reg = np.concatenate([reg[..., 1:], np.zeros_like(reg[..., :1])], axis=-1)
        reg ^= feedback[..., None] * taps
    return reg


def crc_ok(bits, check, poly: int = CRC4_ITU) -> np.ndarray:
    """True where the received ``check`` bits equal the CRC of the received ``bits``."""
    c = _bits("check", check)
    return np.all(crc(bits, poly) == c, axis=-1)


class Transmission(NamedTuple):
    """Every stage of the chain, shapes ``(..., N)`` (bits: ``(..., N, L)`` or ``(..., N, L + r)``)."""

    z: np.ndarray  # ideal measurement h(x) + ζ
    zr: np.ndarray  # after the sensor resolution (3)
    index: np.ndarray  # quantizer cell k in 1..K
    saturated: np.ndarray  # bool: |zr / ω| >= Λ (sent as the extreme cell)
    plaintext: np.ndarray  # uint8 (..., L)
    key: np.ndarray  # uint8 (..., L)
    ciphertext: np.ndarray  # uint8 (..., L)
    checksum: np.ndarray  # uint8 (..., r): CRC of the ciphertext
    received: np.ndarray  # uint8 (..., L + r): ciphertext and CRC after channel bit errors
    decrypted_bits: np.ndarray  # uint8 (..., L): decryption (7) of the received ciphertext
    decrypted: np.ndarray  # z̃ = ω U, NaN where unavailable
    available: np.ndarray  # bool α_s: received and CRC passed
    dropped: np.ndarray  # bool: packet lost
    detected: np.ndarray  # bool: received with a CRC failure (discarded)
    undetected: np.ndarray  # bool: bit errors the CRC missed (a wrong value delivered as available)


def _channel_checks(z, codec, bit_error_prob, dropout_prob, poly) -> tuple[np.ndarray, float, float]:
    z = np.asarray(z, dtype=float)
    if z.ndim < 1 or not np.all(np.isfinite(z)):
        raise InputError(f"z must be a finite array (..., N) of measurements, got shape {z.shape}")
    if not isinstance(codec, Codec):
        raise InputError(f"codec must be a Codec, got {type(codec).__name__}")
    pe = float(check_probability("bit_error_prob", bit_error_prob))
    pd = float(check_probability("dropout_prob", dropout_prob))
    _generator(poly)  # reject a bad polynomial before drawing anything
    return z, pe, pd


def _channel_draws(rng: np.random.Generator, shape, bits: int, r: int, key) -> tuple:
    """``(key, bit uniforms (*shape, bits + r), packet uniforms shape)`` in :func:`transmit`'s draw order."""
    if key is None:
        key = key_stream(rng, shape, bits)
    return key, rng.random(tuple(shape) + (bits + r,)), rng.random(shape)


def _send(z: np.ndarray, codec: Codec, key, flip_u, drop_u, pe: float, pd: float, poly: int) -> Transmission:
    """The chain for given draws (no randomness): every stage of :class:`Transmission`."""
    L = codec.bits
    try:
        zr = codec.resolve(z)
        k = codec.index(zr)
    except ValueError as exc:  # a per-sensor setting that does not broadcast against z
        raise InputError(f"resolution and quant_scale must broadcast against z of shape {z.shape}: {exc}") from None
    plain = to_bits(k, L)
    cipher = encrypt(plain, key)
    check = crc(cipher, poly)
    sent = np.concatenate([cipher, check], axis=-1)
    flips = (flip_u < pe).astype(np.uint8)
    dropped = drop_u < pd
    received = sent ^ flips
    passed = crc_ok(received[..., :L], received[..., L:], poly)
    available = ~dropped & passed
    dec_bits = decrypt(received[..., :L], key)
    value = np.where(available, codec.reconstruct(from_bits(dec_bits)), np.nan)
    corrupted = flips.any(axis=-1)
    return Transmission(z, zr, k, codec.saturated(zr), plain, np.asarray(key, dtype=np.uint8), cipher, check,
                        received, dec_bits, value, available, dropped, ~dropped & ~passed,
                        ~dropped & corrupted & passed)


def transmit(z, codec: Codec, rng: np.random.Generator, *, key=None, bit_error_prob: float = 0.0,
             dropout_prob: float = 0.0, poly: int = CRC4_ITU) -> Transmission:
    """Send measurements ``z`` (..., N) through resolution, quantizer, cipher and a lossy channel.

    Draw order (fixed, so that a seed reproduces a run and different error
    probabilities see the same draws): the key stream (unless ``key`` is given),
    one uniform per transmitted bit (flipped where ``< bit_error_prob``), one uniform
    per packet (dropped where ``< dropout_prob``).
    """
    z, pe, pd = _channel_checks(z, codec, bit_error_prob, dropout_prob, poly)
    check_rng(rng)
    key, flip_u, drop_u = _channel_draws(rng, z.shape, codec.bits, int(poly).bit_length() - 1, key)
    return _send(z, codec, key, flip_u, drop_u, pe, pd, poly)


def transmit_runs(z, codec: Codec, rngs, *, bit_error_prob: float = 0.0, dropout_prob: float = 0.0,
                  poly: int = CRC4_ITU) -> Transmission:
    """:func:`transmit` of every run ``z[r]`` (R, ..., N) with its own Generator ``rngs[r]``, the chain batched.

    Run ``r``'s draws are exactly those of ``transmit(z[r], codec, rngs[r], ...)``, so
    every field equals the stacked per-run transmissions; only the deterministic chain
    (resolution, quantizer, bits, cipher, CRC) runs once over all runs.
    """
    z, pe, pd = _channel_checks(z, codec, bit_error_prob, dropout_prob, poly)
    if isinstance(rngs, np.random.Generator):
        raise InputError("rngs must be a sequence of numpy.random.Generator, one per run (got a single Generator)")
    gens = [check_rng(g) for g in rngs]
    if z.ndim < 2 or len(gens) != z.shape[0]:
        raise InputError(f"z must have shape (runs, ..., N) with one run per Generator ({len(gens)}), got {z.shape}")
    draws = [_channel_draws(g, z.shape[1:], codec.bits, int(poly).bit_length() - 1, None) for g in gens]
    key, flip_u, drop_u = (np.stack(d) for d in zip(*draws))
    return _send(z, codec, key, flip_u, drop_u, pe, pd, poly)


@dataclass(frozen=True, eq=False)
class EncryptedChannel:
    """Seed 001's transmission: the sensors' :class:`Codec` and the errors of the channel.

    Every sensor's measurement goes through the codec's resolution, quantizer and cipher
    with a CRC (:func:`transmit`); each transmitted bit flips with probability
    ``bit_error_prob`` (a CRC failure discards the packet) and each packet is lost with
    probability ``dropout_prob``.  A model file::

        CHANNEL = EncryptedChannel(Codec(resolution=0.2, quant_scale=1.0, quant_levels=8, quant_range=4.0))

    Parameters
    ----------
    codec : Codec
        The sensors' resolution and quantizer (scalars or one value per sensor).
    bit_error_prob, dropout_prob : float in [0, 1)
        Channel errors (0: Assumption 3's perfect channel).
    """

    codec: Codec
    bit_error_prob: float = 0.0
    dropout_prob: float = 0.0

    def __post_init__(self):
        if not isinstance(self.codec, Codec):
            raise InputError(f"EncryptedChannel codec must be a filters.encryption.Codec, got "
                             f"{type(self.codec).__name__}")
        for name in ("bit_error_prob", "dropout_prob"):
            p = check_probability(f"EncryptedChannel {name}", getattr(self, name), open_upper=True)
            if p.ndim:
                raise InputError(f"EncryptedChannel {name} must be a number, got {getattr(self, name)!r}")
            object.__setattr__(self, name, float(p))

    def check(self, model) -> None:
        """That it fits ``model``: scalar sensors, the codec's settings scalars or one per sensor."""
        if any(d != 1 for d in model.sensor_dims):
            raise InputError(f"EncryptedChannel needs scalar sensors (one reading each), the model's have "
                             f"dimensions {list(model.sensor_dims)}")
        bound = self.codec.bound
        if bound.ndim > 1 or bound.size not in (1, model.n_sensors):
            raise InputError(f"EncryptedChannel codec: resolution and quant_scale must be scalars or have one value "
                             f"per sensor ({model.n_sensors}), got shape {bound.shape}")

    def transmit_runs(self, z, rngs, *, poly: int = CRC4_ITU) -> Transmission:
        """:func:`transmit_runs` of ``z`` (R, ..., N) through this channel, run ``r`` drawing from ``rngs[r]``."""
        return transmit_runs(z, self.codec, rngs, bit_error_prob=self.bit_error_prob,
                             dropout_prob=self.dropout_prob, poly=poly)
