"""Every attack and channel simulator of the project, in one place.

* **Consensus channels** (seed 003): DoS and FDI on the node-to-node channels
  (:func:`channel_draws`, :func:`attack_pattern`, :func:`simulate_attacks`), with the
  injected signal of the model's :class:`designer.attacks.FDISignal`.
* **Uplinks** to a fusion centre (the comparison's centralized filters): the same draws'
  diagonal, :func:`uplink_attacks`, and the measurements the centre receives, :func:`receive`.
* **Round-Robin and deception** (seed 000): :func:`round_robin_schedule`,
  :func:`deception_attack`, :func:`round_robin_received`.
* **Binary sensors under DoS, deception and flipping** (seed 002): :func:`binary_sensor_channel`.
* **Bias FDI** (seed 004): :func:`attack_values`, :func:`bias_attack`.

The *laws* a model declares are typed in :mod:`designer.attacks`; these functions draw
their realisations.  All are batched over leading Monte Carlo dimensions and draw only
from the ``numpy.random.Generator`` passed in (seed 001's encryption chain, which is not
an attack, is in :mod:`filters.encryption`).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from designer.attacks import FDISignal
from designer.model import Model
from designer.network import SensorNetwork
from designer.noise import Noise
from designer.validation import InputError, check_finite, check_int, check_probability, check_rng

__all__ = [
    "AttackPattern", "channel_draws", "channel_attacks", "attack_pattern", "simulate_attacks",
    "UplinkAttacks", "uplink_attacks", "receive",
    "round_robin_schedule", "DeceptionOutcome", "deception_attack", "round_robin_received",
    "BinaryOutcome", "binary_sensor_channel",
    "attack_values", "BiasAttack", "bias_attack",
]


# --------------------------------------------------------------------------- consensus channels (seed 003)
class AttackPattern(NamedTuple):
    """Realised attacks: entry ``[k, i, j]`` of ``dos`` and ``fdi`` (bool (steps, N, N)) concerns the channel j -> i at
    time k + 1.  The injected signal is kept where it was injected: ``xi_fdi`` (count, n_x) holds the signals of
    ``fdi``'s true entries in row-major order.  :attr:`xi` is the dense (steps, N, N, n_x) array (zero where no FDI),
    built when asked (784 MB for a run of the 118-bus grid, nearly all zeros); :meth:`xi_of` gives the entries of an
    index without it; :meth:`dense` makes a pattern from a dense ``xi``."""

    dos: np.ndarray
    fdi: np.ndarray
    xi_fdi: np.ndarray

    @classmethod
    def dense(cls, dos, fdi, xi) -> "AttackPattern":
        """The pattern of a dense signal ``xi`` (steps, N, N, n_x): its entries where ``fdi``, the others dropped."""
        fdi = np.asarray(fdi, dtype=bool)
        return cls(np.asarray(dos, dtype=bool), fdi, np.asarray(xi, dtype=float)[fdi])

    @property
    def n_x(self) -> int:
        return int(self.xi_fdi.shape[-1])

    @property
    def xi(self) -> np.ndarray:
        """The dense injected signal (steps, N, N, n_x), zero where no FDI (a new array)."""
        out = np.zeros(self.fdi.shape + (self.n_x,))
        out[self.fdi] = self.xi_fdi
        return out

    def xi_of(self, index) -> np.ndarray:
        """``xi[index]`` for an index of the (steps, N, N) entries, without the dense array."""
        if isinstance(index, (int, np.integer)):  # one step: its entries are one run of xi_fdi, after the steps before
            k = range(self.fdi.shape[0])[index]
            f = self.fdi[k]
            start = int(np.count_nonzero(self.fdi[:k]))
            out = np.zeros(f.shape + (self.n_x,))
            out[f] = self.xi_fdi[start:start + int(np.count_nonzero(f))]
            return out
        f = self.fdi[index]
        out = np.zeros(np.shape(f) + (self.n_x,))
        if np.any(f):
            rank = (np.cumsum(self.fdi.ravel()) - 1).reshape(self.fdi.shape)[index]
            out[f] = self.xi_fdi[rank[f]]
        return out

    def fits(self, n_nodes: int, steps: int | None = None, n_x: int | None = None) -> bool:
        """Whether the pattern holds (steps, n_nodes, n_nodes) channels (``steps``, ``n_x``: when given, those) and
        one signal of ``n_x`` components per falsified entry."""
        d, f, x = np.shape(self.dos), np.shape(self.fdi), np.shape(self.xi_fdi)
        return (len(d) == 3 and d[1:] == (n_nodes, n_nodes) and f == d and (steps is None or d[0] == steps)
                and len(x) == 2 and x[0] == np.count_nonzero(self.fdi) and (n_x is None or x[1] == n_x))

    @staticmethod
    def expected(n_nodes: int, steps: int | None = None, n_x: int | None = None) -> str:
        """What :meth:`fits` asks, in words (a refusal's)."""
        return (f"dos, fdi of shape ({'steps' if steps is None else steps}, {n_nodes}, {n_nodes}) and xi_fdi one "
                f"signal{'' if n_x is None else f' of {n_x} components'} per falsified entry")


def channel_draws(steps: int, n_nodes: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The uniforms ``u`` and normals ``s`` (each ``(steps, N, N)``) behind every channel's attack.

    Entry ``[k, i, j]`` drives the channel ``j -> i``; the diagonal ``[k, i, i]`` is not a
    network channel and is used for node ``i``'s uplink to a fusion centre
    (:func:`uplink_attacks`), so networked and centralized filters can face one
    realisation of the same attack law.
    """
    check_rng(rng)
    u = rng.random((steps, n_nodes, n_nodes))
    s = rng.standard_normal((steps, n_nodes, n_nodes))
    return u, s


def channel_attacks(u: np.ndarray, s: np.ndarray, dos_prob, fdi_prob, n_x: int, signal: FDISignal, on=True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The consensus channels' attack law, channel by channel: ``(dos, fdi, ξ)`` of channels with draws ``u``, ``s``
    (any shape) and probabilities ``dos_prob``, ``fdi_prob`` (broadcast against them), where ``on`` (a channel of
    the network): DoS iff ``u < φ̄``, FDI iff ``φ̄ <= u < φ̄ + γ̄``, ``ξ = a g(s)`` where FDI
    (:meth:`designer.attacks.FDISignal.inject`).  :func:`attack_pattern` applies it to every pair of nodes,
    :meth:`filters.consensus_batch.EdgeAttacks.simulate` to the network's channels alone."""
    dos, fdi = _channel_flags(u, dos_prob, fdi_prob, on)
    return dos, fdi, signal.inject(s, fdi, n_x)


def _channel_flags(u: np.ndarray, dos_prob, fdi_prob, on=True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`channel_attacks`' DoS and FDI flags."""
    dos = on & (u < dos_prob)
    return dos, on & ~dos & (u < dos_prob + fdi_prob)


def attack_pattern(network: SensorNetwork, u: np.ndarray, s: np.ndarray, n_x: int, signal: FDISignal
                   ) -> AttackPattern:
    """Channel attacks from the draws of :func:`channel_draws` (see :func:`simulate_attacks`): the law of
    :func:`channel_attacks`, its signal drawn at the falsified entries alone (the same numbers)."""
    dos, fdi = _channel_flags(u, network.dos_prob[None], network.fdi_prob[None], network.adjacency[None])
    return AttackPattern(dos, fdi, signal.inject(s[fdi], np.ones(np.count_nonzero(fdi), dtype=bool), n_x))


def simulate_attacks(network: SensorNetwork, steps: int, n_x: int, rng: np.random.Generator, signal: FDISignal
                     ) -> AttackPattern:
    """Draw DoS / FDI indicators and the injected signal on every channel and step.

    DoS and FDI are exclusive: with ``u ~ U(0, 1)``, DoS iff ``u < phibar``, FDI iff
    ``phibar <= u < phibar + gammabar``.  The injected signal is ``ξ = a g(s)``
    (:meth:`designer.attacks.FDISignal.inject`), ``s ~ N(0, 1)`` per channel and step, so
    ``||ξ|| <= ||a||``.
    """
    u, s = channel_draws(steps, network.n_nodes, rng)
    return attack_pattern(network, u, s, n_x, signal)


# --------------------------------------------------------------------------- uplinks to a fusion centre
class UplinkAttacks(NamedTuple):
    """Entry ``[k]`` concerns the measurement of ``x_{k+1}``."""

    dos: np.ndarray  # bool (steps, N)
    fdi: np.ndarray  # bool (steps, N)
    xi: np.ndarray  # (steps, N, n_x), zero where no FDI


def uplink_attacks(u: np.ndarray, s: np.ndarray, n_x: int, *, dos_prob, fdi_prob, signal: FDISignal
                   ) -> UplinkAttacks:
    """Uplink attacks from the diagonal of the channel draws ``u``, ``s`` (steps, N, N).

    ``dos_prob``, ``fdi_prob``: a probability for every uplink or one per sensor.
    """
    n = u.shape[-1]
    dos_prob = np.broadcast_to(check_probability("dos_prob", dos_prob), (n,))
    fdi_prob = np.broadcast_to(check_probability("fdi_prob", fdi_prob), (n,))
    if np.any(dos_prob + fdi_prob > 1.0):
        raise InputError(f"dos_prob + fdi_prob must be <= 1 on every uplink, got {dos_prob} + {fdi_prob}")
    u, s = np.diagonal(u, axis1=1, axis2=2), np.diagonal(s, axis1=1, axis2=2)
    dos = u < dos_prob
    fdi = ~dos & (u < dos_prob + fdi_prob)
    return UplinkAttacks(dos, fdi, signal.inject(s, fdi, n_x))


def receive(model: Model, x: np.ndarray, z: np.ndarray, attacks: UplinkAttacks) -> np.ndarray:
    """The centre's measurements ``(steps, n_z + N)`` from the truth ``x`` (steps + 1, n_x) and clean ``z``.

    A falsified packet reads ``z_i + h_i(x + ξ) - h_i(x)`` (for a sensor affine in the
    attacked components, ``z_i + H_i ξ``); a lost one 0.  The last ``N`` columns are each
    sensor's availability α_i in {0, 1} (:func:`filters.uplink.split_received`).
    """
    steps, N = attacks.dos.shape
    if z.shape != (steps, model.n_z) or x.shape != (steps + 1, model.n_x) or N != model.n_sensors:
        raise InputError(f"z must be ({steps}, {model.n_z}) and x ({steps + 1}, {model.n_x}) for {N} uplinks; "
                         f"got z {z.shape}, x {x.shape}, model with {model.n_sensors} sensors")
    y = z.copy()
    offsets = model.sensor_offsets
    for i in range(N):
        a, b = offsets[i], offsets[i + 1]
        for k in np.flatnonzero(attacks.fdi[:, i]):
            y[k, a:b] += model.h(i, x[k + 1] + attacks.xi[k, i], k + 1) - model.h(i, x[k + 1], k + 1)
        y[attacks.dos[:, i], a:b] = 0.0
    return np.concatenate([y, (~attacks.dos).astype(float)], axis=1)


# --------------------------------------------------------------------------- Round-Robin and deception (seed 000)
def round_robin_schedule(steps: int, n_sensors: int, start: int = 1) -> np.ndarray:
    """Sensor with channel access at k = 1..K: ``gamma_k = mod(k + gamma_ini - 2, N) + 1`` (seed 000 (3)).

    Returns 0-based sensor indices of shape (K,); ``start`` is the paper's 1-based ``gamma_ini``.
    """
    n_sensors = check_int("n_sensors", n_sensors, 1)
    if not isinstance(start, (int, np.integer)) or not 1 <= start <= n_sensors:
        raise InputError(f"start (gamma_ini) must be an integer in [1, {n_sensors}], got {start!r}")
    steps = check_int("steps", steps, 1)
    k = np.arange(1, steps + 1)
    return np.mod(k + start - 2, n_sensors)  # (gamma_k - 1)


class DeceptionOutcome(NamedTuple):
    y: np.ndarray  # received values: (1 - eta) y + eta xi
    eta: np.ndarray  # bool, attack succeeded
    xi: np.ndarray  # the deception signal drawn at every step (used where eta)


def deception_attack(y, prob: float, signal: Noise, rng: np.random.Generator) -> DeceptionOutcome:
    """Bernoulli deception (seed 000 (4)-(6)): with probability ``prob`` the packet is replaced by ``xi ~ signal``.

    ``y`` has shape (..., n_y); one Bernoulli per packet (all leading dimensions).
    """
    y = np.asarray(y, dtype=float)
    p = float(check_probability("prob", prob, open_upper=True))
    if y.shape[-1] != signal.dim:
        raise InputError(f"y must have last dimension {signal.dim} (the deception signal's), got {y.shape}")
    eta = rng.random(y.shape[:-1]) < p
    xi = signal.sample(rng, y.shape[:-1])
    return DeceptionOutcome(np.where(eta[..., None], xi, y), eta, xi)


def round_robin_received(y_sched, schedule: np.ndarray, n_sensors: int, strategy: str = "zero-input"):
    """The stacked received vector ``ybar_k`` of seed 000 (7) (zero input) or its zero-order-hold variant.

    ``y_sched`` (..., K, n_y) holds the (possibly attacked) packet of the scheduled sensor
    at each step; the result has shape (..., K, n_sensors, n_y): the scheduled slot holds
    the packet, the others 0 (``zero-input``) or the last packet received from that sensor
    (``zero-order-hold``, 0 before the first one).
    """
    y_sched = np.asarray(y_sched, dtype=float)
    K = y_sched.shape[-2]
    if schedule.shape != (K,):
        raise InputError(f"schedule must have shape ({K},), got {schedule.shape}")
    if strategy not in ("zero-input", "zero-order-hold"):
        raise InputError(f"strategy must be 'zero-input' or 'zero-order-hold', got {strategy!r}")
    out = np.zeros(y_sched.shape[:-2] + (K, n_sensors, y_sched.shape[-1]))
    for k in range(K):
        if strategy == "zero-order-hold" and k > 0:
            out[..., k, :, :] = out[..., k - 1, :, :]
        out[..., k, schedule[k], :] = y_sched[..., k, :]
    return out


# --------------------------------------------------------------------------- binary sensors (seed 002)
class BinaryOutcome(NamedTuple):
    y: np.ndarray  # received signal tau * theta_bar + eps (..., S)
    theta: np.ndarray  # sensor bits before the flip
    theta_bar: np.ndarray  # bits after the flipping attack
    dos: np.ndarray  # bool
    deception: np.ndarray  # bool
    flip: np.ndarray  # bool


def binary_sensor_channel(yhat, *, dos_prob: float, deception_prob: float, flip_prob: float, deception: Noise,
                          threshold: float, gain: float, channel_noise: Noise,
                          rng: np.random.Generator) -> BinaryOutcome:
    """Seed 002 (3)-(7): DoS and deception on the readings, thresholding, bit flipping, noisy channel.

    ``ybar = (1 - phi)(yhat + varphi (mu - yhat))`` with DoS ``phi`` and deception ``varphi``
    (independent Bernoullis, ``mu ~ deception``); ``theta = 1[ybar > threshold]``;
    ``theta_bar = theta`` XOR ``alpha`` (flip); ``y = gain * theta_bar + eps``.
    """
    yhat = np.asarray(yhat, dtype=float)
    pd = float(check_probability("dos_prob", dos_prob, open_upper=True))
    pv = float(check_probability("deception_prob", deception_prob, open_upper=True))
    pf = float(check_probability("flip_prob", flip_prob, open_upper=True))
    if threshold <= 0:
        raise InputError(f"threshold must be > 0, got {threshold!r}")
    shape = yhat.shape
    dos = rng.random(shape) < pd
    dec = rng.random(shape) < pv
    mu = deception.sample(rng, shape)[..., 0]
    ybar = np.where(dos, 0.0, np.where(dec, mu, yhat))
    theta = ybar > threshold
    flip = rng.random(shape) < pf
    theta_bar = theta ^ flip
    eps = channel_noise.sample(rng, shape)[..., 0]
    return BinaryOutcome(gain * theta_bar + eps, theta, theta_bar, dos, dec, flip)


# --------------------------------------------------------------------------- bias FDI (seed 004)
def attack_values(steps: int, bias, tau: float) -> np.ndarray:
    """``γ_1 .. γ_K`` of (4) by its recursion from ``γ_0 = 0``; shape (K, n_y).

    ``γ_k`` is injected into the measurement of step ``k`` (``z[k - 1]`` in the
    project's convention, which measures ``x_k``).
    """
    steps = check_int("steps", steps, 1)
    bias = check_finite("bias", bias)
    if bias.ndim != 1:
        raise InputError(f"bias (gamma-bar) must be a vector, got shape {bias.shape}")
    tau = float(check_finite("tau", tau))
    if not 0.0 < tau < 1.0:
        raise InputError(f"tau must lie in (0, 1), got {tau!r}")
    out = np.empty((steps, bias.size))
    g = np.zeros(bias.size)
    for k in range(steps):
        g = tau * g + (1.0 - tau) * bias
        out[k] = g
    return out


class BiasAttack(NamedTuple):
    y: np.ndarray  # (..., K, n_y) received ỹ_k = y_k + l_k γ_k
    gamma: np.ndarray  # (K, n_y) the attack value γ_k (it evolves whether or not it is injected)
    l: np.ndarray  # (..., K) bool: injected at step k


def bias_attack(y, *, bias, tau: float, prob: float, rng: np.random.Generator) -> BiasAttack:
    """Inject the bias attack (3)-(4) into measurements ``y`` of shape (..., K, n_y).

    One Bernoulli(``prob``) per step and leading index (all sensors attacked together).
    """
    y = check_finite("y", y)
    if y.ndim < 2:
        raise InputError(f"y must have shape (..., K, n_y), got {y.shape}")
    p = float(check_probability("prob", prob))
    check_rng(rng)
    gamma = attack_values(y.shape[-2], bias, tau)
    if gamma.shape[-1] != y.shape[-1]:
        raise InputError(f"bias must have length {y.shape[-1]} (the measurement's), got {gamma.shape[-1]}")
    l = rng.random(y.shape[:-1]) < p
    return BiasAttack(y + l[..., None] * gamma, gamma, l)
