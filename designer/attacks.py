"""The attack specification a model declares: what its channels and uplinks suffer.

A model file declares it next to its ``NETWORK``::

    NETWORK = SensorNetwork.from_edges(6, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0)])
    ATTACKS = AttackSpec(dos=0.1, fdi={(0, 1): 0.3, (2, 3): 0.1},
                         signal=FDISignal(amplitude=0.5, components=(0,)))

and every command can override it (``--dos``, ``--fdi``, ``--delta``, ``--amplitude``).

**Channels** (the consensus filter, seed 003).  Neighbour ``j`` sends its prediction to
node ``i`` over the channel ``j -> i``.  At every step that channel suffers, exclusively,
a denial of service with probability ``dos`` (the packet is lost and node ``i`` knows
it) or a false-data injection with probability ``fdi`` (the injected signal ``ξ`` is
added to the packet, and node ``i`` cannot tell).  ``dos`` and ``fdi`` are each

* a number: the same probability on every channel;
* a mapping ``{(i, j): p}`` over undirected edges: ``p`` on both channels of the edge
  ``i - j``, 0 on the edges not listed;
* an ``(N, N)`` array: entry ``[i, j]`` is the channel ``j -> i`` (entries off the edges
  must be 0).

**The injected signal** (:class:`FDISignal`): ``ξ_c = a_c g(s)`` on the attacked state
components ``c``, with one ``s ~ N(0, 1)`` per channel and step and ``g`` the law:
``'sine'`` (``g = sin``, the paper's ``ξ = [1.5 1.5]ᵀ sin(s)``), ``'uniform'``
(``g = 2 Φ(s) - 1``, uniform on ``[-1, 1]``) or ``'constant'`` (``g = 1``, a fixed bias).
Every law keeps ``‖ξ‖ <= ‖a‖``.  The design's bound ``δ`` on ``‖ξ‖`` is ``delta`` when
given (it must be at least ``‖a‖``), else ``‖a‖``.  An FDI probability > 0 with neither a
signal nor ``delta`` is an error: the bound (27) needs δ.

**Uplinks** (the centralized filters of the comparison).  Sensor ``i`` sends its
measurement to a fusion centre over its own uplink with DoS probability
``uplink_dos[i]`` and FDI probability ``uplink_fdi[i]`` (numbers or one per sensor);
by default each sensor's uplink has the mean probability of the channels into node
``i`` (the channel probability itself when it is the same everywhere).  A falsified
uplink packet reads ``h_i(x + ξ)`` instead of ``h_i(x)``, with the same signal law.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from .network import SensorNetwork, node_pair
from .noise import Noise
from .validation import InputError, check_finite, check_int, check_probability

__all__ = ["FDISignal", "AttackSpec", "SIGNAL_LAWS", "NO_ATTACKS", "RoundRobinDeception", "BinarySensorChannel",
           "BiasFDI"]

# law -> (g(s) as a NumPy function of standard normals, E[g(s)^2])
SIGNAL_LAWS = ("sine", "uniform", "constant")
_SECOND_MOMENT = {"sine": 0.5 * (1.0 - np.exp(-2.0)), "uniform": 1.0 / 3.0, "constant": 1.0}
_MEAN = {"sine": 0.0, "uniform": 0.0, "constant": 1.0}  # E[g(s)]: sin and 2Φ - 1 are odd


def _g(law: str, s: np.ndarray) -> np.ndarray:
    if law == "sine":
        return np.sin(s)
    if law == "uniform":
        from scipy.special import erf

        return erf(s / np.sqrt(2.0))  # 2 Φ(s) - 1
    return np.ones_like(s)


@dataclass(frozen=True)
class FDISignal:
    """The injected signal of a false-data injection: ``ξ_c = a_c g(s)`` on ``components``.

    Parameters
    ----------
    amplitude : float or sequence of float
        ``a``: one amplitude for every attacked component, or one per component (>= 0).
    components : sequence of int, optional
        The state components the signal is added to (default: all of them).
    law : {'sine', 'uniform', 'constant'}
        ``g``: ``sin(s)`` (the paper's), ``2 Φ(s) - 1`` (uniform on [-1, 1]) or ``1``
        (a constant bias), with one ``s ~ N(0, 1)`` per channel and step.
    """

    amplitude: float | Sequence[float]
    components: tuple[int, ...] | None = None
    law: str = "sine"

    def __post_init__(self):
        if self.law not in SIGNAL_LAWS:
            raise InputError(f"FDISignal law must be one of {', '.join(SIGNAL_LAWS)}, got {self.law!r}")
        a = check_finite("FDISignal amplitude", self.amplitude)
        if a.ndim > 1 or np.any(a < 0):
            raise InputError(f"FDISignal amplitude must be a number >= 0 or one per component, got {self.amplitude!r}")
        if self.components is not None:
            try:
                comps = tuple(self.components)
            except TypeError:
                comps = ()
            if not comps or len(set(comps)) != len(comps) or any(
                    isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, np.integer)) or c < 0 for c in comps):
                raise InputError(f"FDISignal components must be distinct integer state indices, got "
                                 f"{self.components!r}")
            comps = tuple(int(c) for c in comps)
            if a.ndim == 1 and a.size != len(comps):
                raise InputError(f"FDISignal amplitude has {a.size} entries but components has {len(comps)}")
            object.__setattr__(self, "components", comps)
        object.__setattr__(self, "amplitude", float(a) if a.ndim == 0 else tuple(float(v) for v in a))

    def resolve(self, n_x: int) -> "FDISignal":
        """This signal with its components and one amplitude per component made explicit for a state of size n_x."""
        comps = tuple(range(n_x)) if self.components is None else self.components
        if any(not 0 <= c < n_x for c in comps):
            raise InputError(f"FDISignal components must index state components 0..{n_x - 1}, got {comps}")
        a = np.broadcast_to(np.asarray(self.amplitude, dtype=float), (len(comps),))
        if a.size != len(comps):
            raise InputError(f"FDISignal amplitude has {a.size} entries but the signal acts on {len(comps)} "
                             "components")
        return FDISignal(tuple(float(v) for v in a), comps, self.law)

    def amplitudes(self, n_x: int) -> np.ndarray:
        """``a`` as a full state vector (0 on the components not attacked)."""
        r = self.resolve(n_x)
        out = np.zeros(n_x)
        out[list(r.components)] = r.amplitude
        return out

    def bound(self, n_x: int) -> float:
        """``sup ‖ξ‖ = ‖a‖`` (every law has ``|g| <= 1``)."""
        r = self.resolve(n_x)
        a = np.asarray(r.amplitude)
        if np.all(a == a[0]):  # a sqrt(n): the paper's "1.5 sqrt(2)", to the last bit
            return float(a[0] * np.sqrt(a.size))
        return float(np.linalg.norm(a))

    @property
    def second_moment(self) -> float:
        """``E[g(s)²]`` of the law."""
        return float(_SECOND_MOMENT[self.law])

    def moment(self, n_x: int) -> np.ndarray:
        """``E[ξ ξᵀ] = E[g²] a aᵀ`` (n_x x n_x): what one falsified packet adds, in the mean square."""
        a = self.amplitudes(n_x)
        return self.second_moment * np.outer(a, a)

    def mean(self, n_x: int) -> np.ndarray:
        """``E[ξ] = E[g] a`` (n_x,): zero for the odd laws, ``a`` for a constant bias."""
        return _MEAN[self.law] * self.amplitudes(n_x)

    def passing(self, c, threshold: float, dim: int, nodes: int = 48) -> tuple[np.ndarray, np.ndarray]:
        """A falsified packet ``d + ξ`` against a χ² gate ``(d + ξ)ᵀ Σ⁻¹ (d + ξ) <= threshold``, ``d ~ N(0, Σ)``.

        ``c = aᵀ Σ⁻¹ a`` (an array, one per packet).  Given ``s`` the statistic is noncentral
        χ²(dim, g(s)² c), so over ``s ~ N(0, 1)`` (Gauss-Hermite, ``nodes`` points) this returns
        ``P(pass)`` and ``E[g(s)² 1{pass}]`` (what a kept falsified packet adds, times ``a aᵀ``).
        """
        from scipy.special import chndtr

        x, w = np.polynomial.hermite_e.hermegauss(nodes)
        w = w / w.sum()
        g2 = _g(self.law, x) ** 2
        F = chndtr(threshold, dim, np.asarray(c, dtype=float)[..., None] * g2)
        return F @ w, (F * g2) @ w

    def span(self, n_x: int) -> np.ndarray:
        """The projector onto the attacked components (n_x x n_x, diagonal 0/1): ``ξ ξᵀ <= ||ξ||² Π``."""
        return np.diag((self.amplitudes(n_x) != 0).astype(float))

    def inject(self, s: np.ndarray, mask: np.ndarray, n_x: int) -> np.ndarray:
        """``ξ`` of shape ``s.shape + (n_x,)``: ``a g(s)`` where ``mask``, 0 elsewhere."""
        return (_g(self.law, s) * mask)[..., None] * self.amplitudes(n_x)

    def scaled_to(self, delta: float, n_x: int) -> "FDISignal":
        """The same law and direction with ``‖a‖ = delta`` (all components equal when ``a = 0``)."""
        r = self.resolve(n_x)
        a = np.asarray(r.amplitude)
        if np.all(a == a[0]):
            a = np.full(a.size, delta / np.sqrt(a.size))
        else:
            a = a * (delta / float(np.linalg.norm(a)))
        return FDISignal(tuple(float(v) for v in a), r.components, r.law)

    def describe(self, state_names: Sequence[str] | None = None) -> dict:
        comps = self.components
        names = None if comps is None or state_names is None else [state_names[c] for c in comps]
        return {"law": self.law, "amplitude": self.amplitude, "components": None if comps is None else list(comps),
                "component_names": names}


def _channel_matrix(name: str, value, network: SensorNetwork) -> np.ndarray:
    """Per-channel probabilities ``[i, j]`` (channel j -> i) from a number, an edge mapping or a matrix."""
    n, adj = network.n_nodes, network.adjacency
    if isinstance(value, Mapping):
        out = np.zeros((n, n))
        given: dict[tuple[int, int], tuple] = {}  # undirected edge -> (key, p) as first given
        for key, p in value.items():
            i, j = node_pair(f"{name}: key", key, n)
            if not adj[i, j]:
                raise InputError(f"{name}: ({i}, {j}) is not an edge of the network (edges: {network.edges})")
            v = _probability(f"{name}[({i}, {j})]", p)
            edge = (min(i, j), max(i, j))
            if edge in given and given[edge][1] != v:
                k0, v0 = given[edge]
                raise InputError(f"{name}: the undirected edge {edge[0]} - {edge[1]} is given twice with different "
                                 f"probabilities, {k0!r}: {v0!r} and {key!r}: {v!r} (a mapping sets both directions "
                                 "of an edge; give an (N, N) array for one per direction)")
            given[edge] = (key, v)
            out[i, j] = out[j, i] = v
        return out
    arr = check_finite(name, value)
    if arr.ndim == 0:
        return np.where(adj, _probability(name, float(arr)), 0.0)
    if arr.shape != (n, n):
        raise InputError(f"{name} must be a number, a mapping {{(i, j): p}} over edges or an ({n}, {n}) array "
                         f"(entry [i, j] = channel j -> i), got shape {arr.shape}")
    bad = np.argwhere((arr != 0) & ~adj)
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise InputError(f"{name}[{i}, {j}] = {arr[i, j]!r} but {j} -> {i} is not a channel of the network")
    for i, j in np.argwhere(adj):
        _probability(f"{name}[{i}, {j}]", arr[i, j])
    return arr.astype(float)


def _probability(name: str, p) -> float:
    try:
        v = float(p)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a probability in [0, 1), got {p!r}") from None
    if not (0.0 <= v < 1.0):
        raise InputError(f"{name} must be a probability in [0, 1), got {p!r}")
    return v


def _uplink(name: str, value, channels: np.ndarray, network: SensorNetwork) -> np.ndarray:
    n = network.n_nodes
    if value is None:  # each node's mean over its incoming channels (exactly their value when they agree)
        out = np.zeros(n)
        for i in range(n):
            p = channels[i, network.adjacency[i]]
            out[i] = 0.0 if p.size == 0 else (p[0] if np.all(p == p[0]) else p.mean())
        return out
    arr = check_finite(name, value)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise InputError(f"{name} must be a number or one probability per sensor ({n}), got shape {arr.shape}")
    for i, p in enumerate(arr):
        _probability(f"{name}[{i}]", p)
    return arr


@dataclass(frozen=True)
class AttackSpec:
    """What the channels between nodes and the sensors' uplinks suffer (see the module docstring).

    Parameters
    ----------
    dos, fdi : float, mapping {(i, j): p} or (N, N) array
        Probabilities of denial of service and of false-data injection per channel
        (exclusive: ``dos + fdi <= 1`` on every channel).
    signal : FDISignal, optional
        The injected signal.  Without it, a given ``delta`` implies the paper's law on
        every state component at the bound (``a_c = delta / sqrt(n_x)``).
    delta : float, optional
        The bound ``‖ξ‖ <= δ`` the design assumes (default: the signal's ``‖a‖``).
    uplink_dos, uplink_fdi : float or sequence (N,), optional
        The centralized filters' uplinks (default: each node's mean over its incoming channels).
    signal_at_delta : bool
        Scale the signal's amplitudes so that ``‖a‖ = delta`` (what ``--delta`` alone does).
    """

    dos: Any = 0.0
    fdi: Any = 0.0
    signal: FDISignal | None = None
    delta: float | None = None
    uplink_dos: Any = None
    uplink_fdi: Any = None
    signal_at_delta: bool = False

    def __post_init__(self):
        if self.signal is not None and not isinstance(self.signal, FDISignal):
            raise InputError(f"AttackSpec signal must be an FDISignal, got {type(self.signal).__name__}")
        for name in ("dos", "fdi", "uplink_dos", "uplink_fdi"):  # the types here, the values on a network
            value = getattr(self, name)
            if value is not None and not isinstance(value, Mapping):
                check_finite(f"AttackSpec {name}", value)
        if self.delta is not None:
            d = check_finite("delta", self.delta)
            if d.ndim != 0 or d < 0:
                raise InputError(f"delta must be a number >= 0, got {self.delta!r}")
            object.__setattr__(self, "delta", float(d))

    # ------------------------------------------------------------------ overrides
    def override(self, *, dos=None, fdi=None, delta=None, amplitude=None) -> "AttackSpec":
        """The spec with command-line style overrides (``None`` keeps the declared value).

        ``dos`` / ``fdi`` set every channel and every uplink; ``amplitude`` sets the
        signal's amplitude on each attacked component (and with it the bound); ``delta``
        sets the bound and, without ``amplitude``, scales the signal to it.
        """
        spec = self
        if dos is not None:
            spec = replace(spec, dos=_probability("dos", dos), uplink_dos=None)
        if fdi is not None:
            spec = replace(spec, fdi=_probability("fdi", fdi), uplink_fdi=None)
        if amplitude is not None:
            a = check_finite("amplitude", amplitude)
            if a.ndim != 0 or a < 0:
                raise InputError(f"amplitude must be a number >= 0, got {amplitude!r}")
            base = spec.signal or FDISignal(0.0)
            spec = replace(spec, signal=FDISignal(float(a), base.components, base.law), delta=None,
                           signal_at_delta=False)
        if delta is not None:
            spec = replace(spec, delta=delta, signal_at_delta=amplitude is None)
        return spec

    # ------------------------------------------------------------------ resolution
    def resolve(self, network: SensorNetwork, n_x: int, *, require_bound: bool = True) -> "ResolvedAttacks":
        """Validate against ``network`` and a state of size ``n_x``; per-channel and per-uplink arrays.

        ``require_bound=False`` accepts an FDI probability > 0 without a bound (``delta`` is
        then None): for a scenario that a command may still give ``--delta`` or ``--amplitude``.
        """
        dos = _channel_matrix("dos", self.dos, network)
        fdi = _channel_matrix("fdi", self.fdi, network)
        both = np.argwhere(dos + fdi > 1.0 + 1e-12)
        if both.size:
            i, j = (int(v) for v in both[0])
            raise InputError(f"dos + fdi must be <= 1 on every channel (DoS and FDI never occur together); channel "
                             f"{j} -> {i} has {dos[i, j]} + {fdi[i, j]}")
        up_dos = _uplink("uplink_dos", self.uplink_dos, dos, network)
        up_fdi = _uplink("uplink_fdi", self.uplink_fdi, fdi, network)
        if np.any(up_dos + up_fdi > 1.0 + 1e-12):
            i = int(np.argmax(up_dos + up_fdi))
            raise InputError(f"uplink_dos + uplink_fdi must be <= 1 at every sensor; sensor {i} has "
                             f"{up_dos[i]} + {up_fdi[i]}")
        signal, delta = self.signal, self.delta
        if signal is not None and self.signal_at_delta and delta is not None:
            signal = signal.scaled_to(delta, n_x)
        if signal is None and delta is not None:
            signal = FDISignal(delta / np.sqrt(n_x))  # the paper's law on every component, at the bound
        if signal is not None:
            signal = signal.resolve(n_x)
            natural = signal.bound(n_x)
            if delta is None:
                delta = natural
            elif delta < natural * (1 - 1e-12):
                raise InputError(f"delta = {delta:g} is below the signal's bound ||a|| = {natural:g}: the design would "
                                 "not bound the injected signal; give delta >= ||a|| or a smaller amplitude")
        any_fdi = bool(np.any(fdi > 0) or np.any(up_fdi > 0))
        if any_fdi and delta is None:
            if require_bound:
                raise MISSING_BOUND
        elif delta is None:
            delta = 0.0
        return ResolvedAttacks(network.with_attacks(dos, fdi), signal or FDISignal(0.0).resolve(n_x),
                               None if delta is None else float(delta), up_dos, up_fdi)

    def describe(self) -> dict:
        def plain(v):
            if isinstance(v, Mapping):
                return [[int(k[0]), int(k[1]), float(p)] for k, p in v.items()]
            return None if v is None else np.asarray(v, dtype=float).tolist()

        sig = self.signal
        return {"dos": plain(self.dos), "fdi": plain(self.fdi), "signal": None if sig is None else sig.describe(),
                "delta": self.delta, "uplink_dos": plain(self.uplink_dos), "uplink_fdi": plain(self.uplink_fdi)}


@dataclass(frozen=True, eq=False)
class ResolvedAttacks:
    """An :class:`AttackSpec` checked against a network: what the filters and simulators use.

    ``network`` carries the per-channel probabilities (``dos_prob``, ``fdi_prob``),
    ``signal`` the resolved injected signal, ``delta`` the design's bound, and
    ``uplink_dos`` / ``uplink_fdi`` one probability per sensor.
    """

    network: SensorNetwork
    signal: FDISignal
    delta: float | None  # None: FDI without a bound yet (AttackSpec.resolve(require_bound=False))
    uplink_dos: np.ndarray = field(repr=False)
    uplink_fdi: np.ndarray = field(repr=False)

    @property
    def any_fdi(self) -> bool:
        return bool(np.any(self.network.fdi_prob > 0) or np.any(self.uplink_fdi > 0))

    def describe(self, state_names: Sequence[str] | None = None) -> dict:
        net = self.network
        uniform = lambda a: float(a.flat[0]) if a.size and np.all(a == a.flat[0]) else None  # noqa: E731
        on_edges = lambda p: [[int(i), int(j), float(p[i, j])] for i, j in np.argwhere(net.adjacency)]  # noqa: E731
        return {
            "dos_prob": uniform(net.dos_prob[net.adjacency]) if net.adjacency.any() else 0.0,
            "fdi_prob": uniform(net.fdi_prob[net.adjacency]) if net.adjacency.any() else 0.0,
            "channels": {"dos": on_edges(net.dos_prob), "fdi": on_edges(net.fdi_prob),
                         "format": "[i, j, p]: channel j -> i"},
            "signal": self.signal.describe(state_names),
            "delta": self.delta,
            "uplink_dos": self.uplink_dos.tolist(),
            "uplink_fdi": self.uplink_fdi.tolist(),
        }


NO_ATTACKS = AttackSpec()
MISSING_BOUND = InputError("fdi probability > 0 but no FDI bound: declare the injected signal (AttackSpec signal="
                           "FDISignal(amplitude=...)) or its bound delta (--delta D or --amplitude A)")


# --------------------------------------------------------------------------- the particle-filter papers' channels
# What the sensors' packets suffer on their way to a (centralized) particle filter, one law per paper.  A model
# file declares one as ``CHANNEL`` (next to its model()); the simulators are in filters.attacks.
def _number(name: str, value, *, low: float | None = None, low_open: bool = False, high: float | None = None,
            high_open: bool = False) -> float:
    v = check_finite(name, value)
    if v.ndim != 0:
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(v)
    if (low is not None and (v <= low if low_open else v < low)) or \
            (high is not None and (v >= high if high_open else v > high)):
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise InputError(f"{name} must lie in {'(' if low_open or low is None else '['}{lo}, {hi}"
                         f"{')' if high_open or high is None else ']'}, got {value!r}")
    return v


def _law(name: str, value, dim: int | None = None) -> Noise:
    if not isinstance(value, Noise):
        raise InputError(f"{name} must be a designer Noise distribution (e.g. UniformBox, Gaussian), got "
                         f"{type(value).__name__}")
    if dim is not None and value.dim != dim:
        raise InputError(f"{name} must be {dim}-dimensional, got dimension {value.dim}")
    return value


def _scalar_sensors(what: str, model) -> None:
    if any(d != 1 for d in model.sensor_dims):
        raise InputError(f"{what} needs scalar sensors (one reading each), the model's have dimensions "
                         f"{list(model.sensor_dims)}")


@dataclass(frozen=True, eq=False)
class RoundRobinDeception:
    """Seed 000's channel: the Round-Robin protocol with randomly occurring deception attacks.

    One sensor transmits per step, in turn: at ``k = 1..K`` sensor
    ``γ_k = mod(k + start - 2, N) + 1`` (3) (``start`` is the paper's 1-based ``γ_ini``).
    The transmitted packet ``y`` is received as ``ỹ = (1 - η) y + η ξ`` (4)-(6):
    ``η ~ Bernoulli(deception_prob)`` (the paper's η̄) per packet, the fake packet
    ``ξ ~ deception`` (the paper: uniform on a box of plausible values).  A model file::

        CHANNEL = RoundRobinDeception(deception_prob=0.2,
                                      deception=UniformBox([-10.0, -np.pi / 2], [80.0, np.pi / 2]))

    Parameters
    ----------
    deception_prob : float in [0, 1)
        η̄.
    deception : designer Noise
        The law of ``ξ``, of the sensors' dimension (every sensor must have the same).
    start : int >= 1
        ``γ_ini``: the sensor (1-based) with the first channel access.
    """

    deception_prob: float
    deception: Noise
    start: int = 1

    def __post_init__(self):
        p = check_probability("RoundRobinDeception deception_prob", self.deception_prob, open_upper=True)
        if p.ndim:
            raise InputError(f"RoundRobinDeception deception_prob must be a number, got {self.deception_prob!r}")
        object.__setattr__(self, "deception_prob", float(p))
        _law("RoundRobinDeception deception", self.deception)
        object.__setattr__(self, "start", check_int("RoundRobinDeception start", self.start, 1))

    def check(self, model) -> None:
        """That it fits ``model``: sensors of one dimension, that of ``deception``; ``start`` a sensor."""
        dims = sorted(set(model.sensor_dims))
        if len(dims) != 1:
            raise InputError(f"RoundRobinDeception needs sensors of one dimension (one packet type), the model's "
                             f"have dimensions {list(model.sensor_dims)}")
        _law("RoundRobinDeception deception", self.deception, dims[0])
        if self.start > model.n_sensors:
            raise InputError(f"RoundRobinDeception start must be a sensor in [1, {model.n_sensors}], got "
                             f"{self.start}")


@dataclass(frozen=True, eq=False)
class BinarySensorChannel:
    """Seed 002's channel: binary (thresholded) sensors under DoS, deception and bit flipping (3)-(7).

    Each sensor's reading ``ŷ`` is independently jammed with probability ``dos_prob``
    (φ̄; it becomes 0) or else replaced with probability ``deception_prob`` (ϕ̄) by
    ``μ ~ deception``; the sensor sends the bit ``θ = 1[ȳ > threshold]``, flipped with
    probability ``flip_prob`` (ᾱ), over a channel that receives ``y = gain θ̄ + ε``,
    ``ε ~ channel_noise``.  A model file::

        CHANNEL = BinarySensorChannel(dos_prob=0.1, deception_prob=0.1, flip_prob=0.1,
                                      deception=UniformBox([-3.0], [3.0]), threshold=0.3, gain=0.5,
                                      channel_noise=Gaussian.zero_mean([[0.01]]))

    Parameters
    ----------
    dos_prob, deception_prob, flip_prob : float in [0, 1)
        φ̄, ϕ̄, ᾱ.
    deception : designer Noise
        The one-dimensional law of a deceptive reading ``μ``.
    threshold : float > 0
        ``T_δ``.
    gain : float > 0
        ``τ_s``: the received level of a 1 bit.
    channel_noise : designer Noise
        The one-dimensional channel noise ``ε``.
    """

    dos_prob: float
    deception_prob: float
    flip_prob: float
    deception: Noise
    threshold: float
    gain: float
    channel_noise: Noise

    def __post_init__(self):
        for name in ("dos_prob", "deception_prob", "flip_prob"):
            p = check_probability(f"BinarySensorChannel {name}", getattr(self, name), open_upper=True)
            if p.ndim:
                raise InputError(f"BinarySensorChannel {name} must be a number, got {getattr(self, name)!r}")
            object.__setattr__(self, name, float(p))
        _law("BinarySensorChannel deception", self.deception, 1)
        _law("BinarySensorChannel channel_noise", self.channel_noise, 1)
        object.__setattr__(self, "threshold", _number("BinarySensorChannel threshold", self.threshold, low=0.0,
                                                      low_open=True))
        object.__setattr__(self, "gain", _number("BinarySensorChannel gain", self.gain, low=0.0, low_open=True))

    @property
    def probabilities(self) -> tuple[float, float, float]:
        """``(dos_prob, deception_prob, flip_prob)``."""
        return self.dos_prob, self.deception_prob, self.flip_prob

    def check(self, model) -> None:
        """That it fits ``model``: scalar sensors."""
        _scalar_sensors("BinarySensorChannel", model)


@dataclass(frozen=True, eq=False)
class BiasFDI:
    """Seed 004's attack: a bias injected into every measurement at random steps (3)-(4).

    ``ỹ_k = y_k + l_k γ_k`` with ``l_k ~ Bernoulli(prob)`` per step (all sensors
    together) and ``γ_{k+1} = tau γ_k + (1 - tau) bias``, ``γ_0 = 0``.  The detectors
    are designed for attacks of norm at least ``norm_min`` (``‖γ‖_min`` of (45)); an
    attack estimate ``γ̂_k = γ_k + e_k``, ``e_k ~ N(0, estimate_var I)``, is the
    noisy-estimate case (the paper's Fig. 13).  A model file::

        CHANNEL = BiasFDI(prob=0.5, bias=[0.5, 0.5, 0.5, 0.5], tau=0.9, norm_min=0.28)

    Parameters
    ----------
    prob : float in [0, 1]
        ``p_l``.
    bias : sequence of float
        ``γ̄``, one entry per measurement component (the model's ``n_z``).
    tau : float in (0, 1)
        The rate of the attack dynamics.
    norm_min : float > 0
        ``‖γ‖_min``.
    estimate_var : float >= 0
        Variance per component of the attack estimate's error (default the paper's 1e-2).
    """

    prob: float
    bias: Sequence[float]
    tau: float
    norm_min: float
    estimate_var: float = 1e-2

    def __post_init__(self):
        p = check_probability("BiasFDI prob", self.prob)
        if p.ndim:
            raise InputError(f"BiasFDI prob must be a number, got {self.prob!r}")
        object.__setattr__(self, "prob", float(p))
        bias = check_finite("BiasFDI bias", self.bias).astype(float)
        if bias.ndim != 1 or bias.size < 1:
            raise InputError(f"BiasFDI bias must be a vector (one entry per measurement component), got "
                             f"{self.bias!r}")
        bias.flags.writeable = False
        object.__setattr__(self, "bias", bias)
        object.__setattr__(self, "tau", _number("BiasFDI tau", self.tau, low=0.0, low_open=True, high=1.0,
                                                high_open=True))
        object.__setattr__(self, "norm_min", _number("BiasFDI norm_min", self.norm_min, low=0.0, low_open=True))
        object.__setattr__(self, "estimate_var", _number("BiasFDI estimate_var", self.estimate_var, low=0.0))

    def check(self, model) -> None:
        """That it fits ``model``: one bias entry per measurement component."""
        if self.bias.size != model.n_z:
            raise InputError(f"BiasFDI bias has {self.bias.size} entries but the model measures {model.n_z} "
                             "components")
