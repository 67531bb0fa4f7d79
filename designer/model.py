"""The symbolic model layer: one CasADi definition, every numeric view of it.

A model is written once with CasADi SX expressions::

    x_{k+1} = f(x_k, k, u_k, r_k) + G w_k,     w_k ~ process_noise
    z_{i,k} = h_i(x_k, k) + v_{i,k},           v_{i,k} ~ sensors[i].noise
    x_0 ~ prior

where ``u_k`` are known inputs and ``r_k`` an optional discrete mode drawn
independently at every step with probabilities ``mode_probs`` (randomly
switching nonlinearities).  From that single definition :class:`Model` builds,
once, the CasADi functions (values, Jacobians ``F``, ``H_i`` and Hessians by
automatic differentiation) and their vectorised NumPy translations for particle
arrays of shape ``(..., n_x)``.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Sequence

import casadi as ca
import numpy as np

from .codegen import to_numpy
from .noise import Noise
from .validation import InputError, ModelWarning, check_finite, check_int, check_type

__all__ = ["Sensor", "Model"]


@dataclass(frozen=True, eq=False)
class Sensor:
    """One sensor: a symbolic measurement function and its additive noise.

    Parameters
    ----------
    name : str
        Label used in results and files.
    h : casadi.SX
        Column expression of the model's state symbol (and optionally of the
        time symbol ``k``).
    noise : Noise
        Additive measurement noise, of the same dimension as ``h``.
    position : sequence of float, optional
        Where the sensor is, for figures and descriptions only.
    angles : sequence of int
        The components of ``h`` that are angles in radians: every filter wraps their
        residuals into (-π, π] (a bearing that crosses ±π is not a 2π error).
    """

    name: str
    h: ca.SX
    noise: Noise
    position: tuple[float, ...] | None = None
    angles: tuple[int, ...] = ()

    def __post_init__(self):
        check_type("Sensor name", self.name, str, "a str")
        h = _column(f"sensor {self.name!r}: h", self.h)
        check_type(f"sensor {self.name!r}: noise", self.noise, Noise, "a designer noise (e.g. Gaussian)")
        try:
            angles = tuple(self.angles)
        except TypeError:
            raise InputError(f"sensor {self.name!r}: angles must be component indices, got {self.angles!r}") from None
        dim = int(h.shape[0])
        if any(isinstance(a, (bool, np.bool_)) or not isinstance(a, (int, np.integer)) or not 0 <= a < dim
               for a in angles) or len(set(angles)) != len(angles):
            raise InputError(f"sensor {self.name!r}: angles must be distinct integer components in 0..{dim - 1}, "
                             f"got {self.angles!r}")
        object.__setattr__(self, "h", h)
        object.__setattr__(self, "angles", tuple(int(a) for a in angles))

    @property
    def dim(self) -> int:
        return int(self.h.shape[0])

    def undeclared_angles(self) -> tuple[int, ...]:
        """The components of ``h`` that are computed with an ``atan2`` but not declared in ``angles``.

        An ``atan2`` jumps by 2π across ±π; a component that passes it on other than through
        ``sin``, ``cos`` or ``tan`` (which do not see the jump) is an angle whose residual
        needs wrapping.  Found in the CasADi expression graph of each component.
        """
        h = self.h if isinstance(self.h, ca.SX) else ca.SX(self.h)
        return tuple(j for j in range(self.dim) if j not in self.angles and _passes_atan2(h[j]))


_PERIODIC = (ca.OP_SIN, ca.OP_COS, ca.OP_TAN)
_NONNEGATIVE = (ca.OP_SQRT, ca.OP_FABS, ca.OP_SQ, ca.OP_HYPOT, ca.OP_EXP)


def _nonnegative(e: ca.SX, depth: int = 8) -> bool:
    """Whether the scalar ``e`` is >= 0 by its form (a sqrt, an absolute value, a square, sums and products of them)."""
    if e.is_constant():
        return float(ca.DM(e)) >= 0.0
    if e.is_leaf() or depth == 0:
        return False
    if e.op() in _NONNEGATIVE:
        return True
    return e.op() in (ca.OP_ADD, ca.OP_MUL) and all(_nonnegative(e.dep(i), depth - 1) for i in range(2))


def _passes_atan2(expr: ca.SX) -> bool:
    """Whether the scalar ``expr`` contains an ``atan2(y, x)`` that can jump at +-pi (``x`` not >= 0 by its form, as
    it is for an elevation) and reaches it other than through sin, cos or tan."""
    stack, seen = [expr], set()
    while stack:
        e = stack.pop()
        key = e.element_hash()
        if key in seen or e.is_leaf():
            continue
        seen.add(key)
        op = e.op()
        if op == ca.OP_ATAN2 and not _nonnegative(e.dep(1)):
            return True
        if op not in _PERIODIC:
            stack.extend(e.dep(i) for i in range(e.n_dep()))
    return False


def _symbol(name: str, value, size: int | None = None) -> ca.SX:
    if value is None:
        return ca.SX.sym(name, 0 if size is None else size)
    if not isinstance(value, ca.SX):
        raise InputError(f"{name} must be a casadi.SX symbol, got {type(value).__name__}")
    if not value.is_symbolic() or value.shape[1] != 1:
        raise InputError(f"{name} must be a purely symbolic column vector (casadi.SX.sym)")
    return value


def _column(name: str, expr, rows: int | None = None) -> ca.SX:
    if isinstance(expr, ca.MX):
        raise InputError(f"{name} must be a casadi.SX expression (an MX expression was given: build the model with "
                         "casadi.SX.sym)")
    if not isinstance(expr, ca.SX):
        try:
            expr = ca.SX(expr)
        except Exception:
            raise InputError(f"{name} must be a casadi.SX expression, got {type(expr).__name__}") from None
    if expr.shape[1] != 1 and expr.shape[0] == 1:
        expr = expr.T
    if expr.shape[1] != 1:
        raise InputError(f"{name} must be a column vector, got shape {expr.shape}")
    if rows is not None and expr.shape[0] != rows:
        raise InputError(f"{name} must have {rows} rows, got {expr.shape[0]}")
    return expr


def _function(name: str, inputs, names, outputs, out_names, what: str | None = None) -> ca.Function:
    # Common subexpressions (e.g. sin(theta) in every camera) are merged once here,
    # so that both CasADi and the NumPy translation evaluate them once.
    outputs = [ca.cse(o) for o in outputs]
    try:
        return ca.Function(name, inputs, outputs, names, out_names)
    except RuntimeError as exc:
        msg = str(exc)
        if "free variables" in msg or "free" in msg:
            raise InputError(
                f"{what or name} depends on symbols other than {', '.join(names)}; "
                "declare every symbol the expressions use"
            ) from None
        raise


class Model:
    """A state-space model defined once, symbolically.

    Parameters
    ----------
    name : str
        Model name.
    x : casadi.SX
        State symbol, ``casadi.SX.sym('x', n_x)``.
    f : casadi.SX
        Transition expression (``n_x`` rows) in ``x`` and optionally ``k``, ``u``, ``mode``.
    sensors : sequence of Sensor
        One entry per sensor; ``h`` may use ``x`` and ``k``.
    process_noise : Noise
        Distribution of ``w_k``.
    prior : Noise
        Distribution of ``x_0``.
    k : casadi.SX, optional
        Scalar time symbol used by ``f`` or ``h`` (time-varying models).
    u : casadi.SX, optional
        Known input symbol used by ``f``.
    mode : casadi.SX, optional
        Scalar discrete mode symbol used by ``f`` (values ``0 .. len(mode_probs)-1``).
    mode_probs : sequence of float, optional
        Probability of each mode, drawn independently at every step.
    noise_gain : array_like, shape (n_x, n_w), optional
        Matrix ``G`` through which the process noise enters (identity by default).
    state_names : sequence of str, optional
        Names of the state components.
    position_index, velocity_index : sequence of int, optional
        Which state components are positions and velocities (for RMSE_p, RMSE_v).
    """

    def __init__(
        self,
        name: str,
        x: ca.SX,
        f,
        sensors: Sequence[Sensor],
        process_noise: Noise,
        prior: Noise,
        *,
        k: ca.SX | None = None,
        u: ca.SX | None = None,
        mode: ca.SX | None = None,
        mode_probs: Sequence[float] | None = None,
        noise_gain=None,
        state_names: Sequence[str] | None = None,
        position_index: Sequence[int] = (),
        velocity_index: Sequence[int] = (),
        description: str = "",
    ):
        self.name = check_type("name", name, str, "a str")
        self.description = description
        self.x = _symbol("x", x)
        self.n_x = int(self.x.shape[0])
        if self.n_x < 1:
            raise InputError("x must have at least one component")
        self.k = _symbol("k", k, 1)
        if self.k.shape[0] != 1:
            raise InputError("k must be a scalar symbol")
        self.u = _symbol("u", u)
        self.n_u = int(self.u.shape[0])
        self.mode = _symbol("mode", mode)
        if self.mode.shape[0] not in (0, 1):
            raise InputError("mode must be a scalar symbol")
        self.f_expr = _column("f", f, self.n_x)

        if self.mode.shape[0] == 1:
            if mode_probs is None:
                raise InputError("mode_probs must be given when the model has a mode symbol")
            p = check_finite("mode_probs", mode_probs).ravel()
            if p.size < 1 or np.any(p < 0) or abs(p.sum() - 1.0) > 1e-9:
                raise InputError("mode_probs must be non-negative and sum to 1")
            self.mode_probs = p / p.sum()
        else:
            if mode_probs is not None:
                raise InputError("mode_probs given but the model has no mode symbol")
            self.mode_probs = None

        if not isinstance(process_noise, Noise):
            raise InputError("process_noise must be a Noise distribution")
        if not isinstance(prior, Noise) or prior.dim != self.n_x:
            raise InputError(f"prior must be a Noise distribution of dimension {self.n_x}")
        self.process_noise = process_noise
        self.prior = prior
        if noise_gain is None:
            if process_noise.dim != self.n_x:
                raise InputError(
                    f"process_noise has dimension {process_noise.dim} but the state has {self.n_x}; "
                    "give noise_gain"
                )
            self.noise_gain = np.eye(self.n_x)
        else:
            G = check_finite("noise_gain", noise_gain)
            if G.shape != (self.n_x, process_noise.dim):
                raise InputError(f"noise_gain must have shape ({self.n_x}, {process_noise.dim}), got {G.shape}")
            self.noise_gain = G

        sensors = tuple(check_type("sensors", sensors, (list, tuple), "a list of designer.Sensor"))
        if not sensors:
            raise InputError("sensors must contain at least one Sensor")
        for i, s in enumerate(sensors):
            if not isinstance(s, Sensor):
                raise InputError(f"sensors[{i}] must be a Sensor")
            _column(f"sensors[{i}].h", s.h)
            if s.noise.dim != s.dim:
                raise InputError(f"sensors[{i}].noise has dimension {s.noise.dim}, its h has {s.dim}")
        names = [s.name for s in sensors]
        if len(set(names)) != len(names):
            raise InputError("sensor names must be unique")
        undeclared = [(s, s.undeclared_angles()) for s in sensors]
        undeclared = [(s, comps) for s, comps in undeclared if comps]
        if undeclared:  # one warning for the model, naming every sensor
            named = ", ".join(repr(s.name) for s, _ in undeclared[:8]) + \
                (f" and {len(undeclared) - 8} more" if len(undeclared) > 8 else "")
            s, comps = undeclared[0]
            warnings.warn(f"sensor{'s' if len(undeclared) > 1 else ''} {named}: an atan2 angle in h is not declared "
                          "in angles=, so its residuals are not wrapped into (-pi, pi] and an angle crossing +-pi is "
                          f"a 2 pi error; declare it, e.g. Sensor({s.name!r}, ..., "
                          f"angles={tuple(sorted(s.angles + comps))})", ModelWarning, stacklevel=2)
        self.sensors = sensors
        self.state_names = tuple(state_names) if state_names else tuple(f"x{i + 1}" for i in range(self.n_x))
        if len(self.state_names) != self.n_x:
            raise InputError(f"state_names must have {self.n_x} entries")
        for label, idx in (("position_index", position_index), ("velocity_index", velocity_index)):
            if any(not (0 <= int(i) < self.n_x) for i in idx):
                raise InputError(f"{label} must index state components 0..{self.n_x - 1}")
        self.position_index = tuple(int(i) for i in position_index)
        self.velocity_index = tuple(int(i) for i in velocity_index)
        self._build()

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        x, k, u, r = self.x, self.k, self.u, self.mode
        fin, fnames = [x, k, u, r], ["x", "k", "u", "mode"]
        f = self.f_expr
        F = ca.jacobian(f, x)
        self.casadi_f = _function("f", fin, fnames, [f], ["x_next"], "the transition f")
        self.casadi_F = _function("F", fin, fnames, [F], ["F"])
        self.casadi_f_hess = _function(
            "f_hess", fin, fnames, [ca.hessian(f[j], x)[0] for j in range(self.n_x)],
            [f"d2f{j}" for j in range(self.n_x)],
        )
        hin, hnames = [x, k], ["x", "k"]
        self.casadi_h, self.casadi_H, self.casadi_h_hess = [], [], []
        for i, s in enumerate(self.sensors):
            h = _column(f"sensors[{i}].h", s.h)
            self.casadi_h.append(_function(f"h{i}", hin, hnames, [h], ["z"], f"sensor {s.name!r}: h"))
            self.casadi_H.append(_function(f"H{i}", hin, hnames, [ca.jacobian(h, x)], ["H"]))
            self.casadi_h_hess.append(
                _function(f"h{i}_hess", hin, hnames, [ca.hessian(h[j], x)[0] for j in range(s.dim)],
                          [f"d2h{j}" for j in range(s.dim)])
            )
        h_all = ca.vertcat(*[s.h for s in self.sensors])
        self.casadi_h_all = _function("h_all", hin, hnames, [h_all], ["z"])
        self.casadi_H_all = _function("H_all", hin, hnames, [ca.jacobian(h_all, x)], ["H"])

        self._np_f = to_numpy(self.casadi_f)
        self._np_F = to_numpy(self.casadi_F)
        self._np_f_hess = to_numpy(self.casadi_f_hess)
        self._np_h = [to_numpy(fn) for fn in self.casadi_h]
        self._np_H = [to_numpy(fn) for fn in self.casadi_H]
        self._np_h_hess = [to_numpy(fn) for fn in self.casadi_h_hess]
        self._np_h_all = to_numpy(self.casadi_h_all)
        self._blocks: dict = {}  # hessian_blocks, built on first use
        rows, cols = F.sparsity().get_triplet()
        self._F_diagonal = all(r == c for r, c in zip(rows, cols))  # each state's next value reads itself alone
        self._dims = tuple(s.dim for s in self.sensors)  # asked per node and step by the filters: computed once
        self._offsets = np.concatenate([[0], np.cumsum(self._dims)])

    # ------------------------------------------------------------ properties
    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    @property
    def sensor_dims(self) -> tuple[int, ...]:
        return self._dims

    @property
    def n_z(self) -> int:
        """Total measurement dimension over all sensors."""
        return int(self._offsets[-1])

    @property
    def sensor_offsets(self) -> np.ndarray:
        """Where each sensor's rows start in the stacked measurement ``z`` (n_sensors + 1,): sensor ``i``'s rows are
        ``z[..., offsets[i]:offsets[i + 1]]`` (a copy)."""
        return self._offsets.copy()

    def sensor_rows(self, i: int) -> slice:
        """Sensor ``i``'s rows of the stacked measurement ``z`` (its measurement is ``z[..., model.sensor_rows(i)]``;
        node ``i`` of a network owns sensor ``i``)."""
        i = check_int("sensor", i, 0, self.n_sensors - 1)
        return slice(int(self._offsets[i]), int(self._offsets[i + 1]))

    @property
    def angle_components(self) -> tuple[tuple[int, int], ...]:
        """``(sensor, component)`` pairs of the angular measurement components (see :class:`Sensor`)."""
        return tuple((i, a) for i, s in enumerate(self.sensors) for a in s.angles)

    @property
    def n_modes(self) -> int:
        return 0 if self.mode_probs is None else len(self.mode_probs)

    @property
    def process_cov(self) -> np.ndarray:
        """Covariance ``G Q Gᵀ`` of the process noise as it enters the state."""
        G = self.noise_gain
        return G @ self.process_noise.cov @ G.T

    def measurement_cov(self, i: int) -> np.ndarray:
        return self.sensors[self._sensor(i)].noise.cov

    # ------------------------------------------------------------- argument checks
    def _sensor(self, i) -> int:
        if not isinstance(i, (int, np.integer)) or not 0 <= i < self.n_sensors:
            raise InputError(f"sensor index must be an integer in 0..{self.n_sensors - 1}, got {i!r}")
        return int(i)

    def _state(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if x.ndim == 0 or x.shape[-1] != self.n_x:
            raise InputError(f"x must have shape (..., {self.n_x}), got {x.shape}")
        if not np.isfinite(x).all():
            raise InputError("x must be finite (no NaN or inf states)")
        return x

    def _u(self, u) -> np.ndarray:
        if self.n_u == 0:
            if u is not None and np.size(u) != 0:
                raise InputError("u given but the model has no inputs")
            return np.zeros(0)
        if u is None:
            raise InputError(f"u (known input of length {self.n_u}) is required by model {self.name!r}")
        u = np.asarray(u, dtype=np.float64)
        if u.ndim == 0 or u.shape[-1] != self.n_u:
            raise InputError(f"u must have shape (..., {self.n_u}), got {u.shape}")
        return u

    def _mode(self, mode) -> np.ndarray:
        if self.mode_probs is None:
            if mode is not None:
                raise InputError("mode given but the model has no switching modes")
            return np.zeros(0)
        if mode is None:
            raise InputError(f"mode (0..{self.n_modes - 1}) is required by switching model {self.name!r}")
        m = np.asarray(mode, dtype=np.float64)
        if np.any((m < 0) | (m >= self.n_modes) | (m != np.round(m))):
            raise InputError(f"mode must be an integer in 0..{self.n_modes - 1}")
        return m[..., None]

    @staticmethod
    def _k(k) -> np.ndarray:
        return np.asarray(k, dtype=np.float64)[..., None]

    # ----------------------------------------------------------- evaluation
    def _mode_average(self, fn, x, k, u) -> np.ndarray:
        if self.mode_probs is None:
            return fn(x, k, u)
        return sum(p * fn(x, k, u, m) for m, p in enumerate(self.mode_probs))

    def f(self, x, k=0, u=None, mode=None) -> np.ndarray:
        """Transition ``f(x, k, u, mode)`` for states of shape ``(..., n_x)``."""
        with np.errstate(all="ignore"):
            return self._np_f(self._state(x), self._k(k), self._u(u), self._mode(mode))[0]

    def f_expected(self, x, k=0, u=None) -> np.ndarray:
        """Transition averaged over the switching modes (``f`` itself without modes)."""
        return self._mode_average(self.f, x, k, u)

    def F(self, x, k=0, u=None, mode=None) -> np.ndarray:
        """Jacobian ``df/dx``, shape ``(..., n_x, n_x)``."""
        with np.errstate(all="ignore"):
            return self._matrix(self._np_F(self._state(x), self._k(k), self._u(u), self._mode(mode))[0], self.n_x)

    def propagate(self, F: np.ndarray, P: np.ndarray) -> np.ndarray:
        """``F P Fᵀ`` of Jacobians ``F`` (..., m, m) of these dynamics (the whole state's, or those of states whose
        dynamics read no other) and covariances ``P`` (..., m, m).  Where CasADi's Jacobian of the dynamics is
        structurally diagonal (each state's next value reads itself alone: a random walk, a decay, a grid's angles),
        by elements, ``F_ii P_ij F_jj``: the products' numbers (each of their sums has one term that is not an exact
        zero), in n² in place of 2 n³ (the 118-bus grid's 118 nodes of 117 states, two runs: 26 → 2.7 ms a call)."""
        if self._F_diagonal:
            d = np.diagonal(F, axis1=-2, axis2=-1)
            return d[..., :, None] * P * d[..., None, :]
        return F @ P @ np.swapaxes(F, -1, -2)

    def _matrix(self, out: np.ndarray, rows: int) -> np.ndarray:
        """A matrix output ``(..., rows, n_x)``: the translation returns a column (one column: ``n_x = 1``) flat."""
        return out[..., None] if self.n_x == 1 and out.shape[-1:] == (rows,) else out

    def F_expected(self, x, k=0, u=None) -> np.ndarray:
        """Jacobian of :meth:`f_expected`."""
        return self._mode_average(self.F, x, k, u)

    def f_hessian(self, x, k=0, u=None, mode=None) -> np.ndarray:
        """Hessians of every component of ``f``, shape ``(..., n_x, n_x, n_x)`` (component first)."""
        with np.errstate(all="ignore"):
            parts = self._np_f_hess(self._state(x), self._k(k), self._u(u), self._mode(mode))
        return np.stack([self._matrix(p, self.n_x) for p in parts], axis=-3)

    def h(self, i: int, x, k=0) -> np.ndarray:
        """Measurement function of sensor ``i``, shape ``(..., n_z_i)``."""
        with np.errstate(all="ignore"):
            return self._np_h[self._sensor(i)](self._state(x), self._k(k))[0]

    def H(self, i: int, x, k=0) -> np.ndarray:
        """Jacobian ``dh_i/dx``, shape ``(..., n_z_i, n_x)``."""
        i = self._sensor(i)
        with np.errstate(all="ignore"):
            return self._matrix(self._np_H[i](self._state(x), self._k(k))[0], self._dims[i])

    def h_hessian(self, i: int, x, k=0) -> np.ndarray:
        """Hessians of every component of ``h_i``, shape ``(..., n_z_i, n_x, n_x)``."""
        with np.errstate(all="ignore"):
            parts = self._np_h_hess[self._sensor(i)](self._state(x), self._k(k))
        return np.stack([self._matrix(p, self.n_x) for p in parts], axis=-3)

    def hessian_blocks(self, sensor: int | None = None) -> tuple[tuple[np.ndarray, ...], Callable]:
        """The Hessians of ``f``'s components (``sensor`` None) or of sensor ``sensor``'s, each on its structural
        support: ``(supports, at)``, ``supports[j]`` the state indices of component ``j``'s structural nonzeros
        (its Hessian is zero outside ``supports[j] x supports[j]``; empty for a component linear in the state) and
        ``at(x, k=0, u=None, mode=None)`` the list of blocks ``(..., |S_j|, |S_j|)``.  On a field or a grid each
        component involves a few states: blocks of a few numbers where :meth:`f_hessian` fills ``n_x²`` per
        component.  Built on first use and kept."""
        key = "f" if sensor is None else self._sensor(sensor)
        if key not in self._blocks:
            fun = self.casadi_f_hess if sensor is None else self.casadi_h_hess[key]
            ins = [self.x, self.k, self.u, self.mode][:fun.n_in()]
            outs = fun(*ins)
            outs = outs if isinstance(outs, (list, tuple)) else [outs]
            supports = []
            for o in outs:
                rows, cols = o.sparsity().get_triplet()
                supports.append(np.unique(np.asarray(rows + cols, dtype=int)))
            blocks = [o[list(S), list(S)] if S.size else ca.SX(0, 0) for o, S in zip(outs, supports)]
            np_fun = to_numpy(_function(f"{fun.name()}_blocks", ins, [fun.name_in(i) for i in range(len(ins))],
                                        blocks, [f"b{j}" for j in range(len(blocks))]))

            def at(x, k=0, u=None, mode=None, np_fun=np_fun, sizes=tuple(S.size for S in supports), n=len(ins)):
                args = (self._state(x), self._k(k)) + ((self._u(u), self._mode(mode)) if n > 2 else ())
                with np.errstate(all="ignore"):
                    parts = np_fun(*args)
                lead = np.shape(args[0])[:-1]
                return [np.reshape(p, lead + (m, m)) for p, m in zip(parts, sizes)]

            self._blocks[key] = (tuple(supports), at)
        return self._blocks[key]

    def h_all(self, x, k=0) -> np.ndarray:
        """All sensors' measurement functions stacked, shape ``(..., n_z)``."""
        with np.errstate(all="ignore"):
            return self._np_h_all(self._state(x), self._k(k))[0]

    def split(self, z) -> list[np.ndarray]:
        """Split a stacked measurement ``(..., n_z)`` into one array per sensor."""
        z = np.asarray(z)
        return [z[..., a:b] for a, b in zip(self._offsets[:-1], self._offsets[1:])]

    def measurement_logpdf(self, i: int, z, x, k=0) -> np.ndarray:
        """``log p(z_i | x)`` for particles ``x`` of shape ``(..., n_x)``."""
        i = self._sensor(i)
        return self.sensors[i].noise.logpdf(np.asarray(z, dtype=float) - self.h(i, x, k))

    def check_finite_at(self, x0, u0=None) -> None:
        """Refuse (:class:`InputError`, naming the sensor) a model that cannot be linearised at its operating point.

        At ``x0`` (step 0) ``f``, its Jacobian and Hessians (every mode), and at ``x0`` and its
        prediction ``f(x0)`` (step 1, where the filters' first update and the design's scalings
        evaluate them) every sensor's ``h``, Jacobian ``H`` and Hessians must be finite: a
        range sensor placed exactly at the point has no Jacobian there (sqrt at 0).
        """
        x0 = self._state(x0)
        u = None if self.n_u == 0 else u0
        modes = [None] if self.mode_probs is None else list(range(self.n_modes))

        def where(x):
            return "x = [" + ", ".join(f"{v:.6g}" for v in np.asarray(x)) + "]"

        for mode in modes:
            at = f" (mode {mode})" if mode is not None else ""
            for what, fn in (("f", self.f), ("the Jacobian df/dx", self.F), ("the Hessians of f", self.f_hessian)):
                if not np.all(np.isfinite(fn(x0, 0, u, mode))):
                    raise InputError(f"the transition: {what} is not finite at the operating point {where(x0)}{at}")
        xp = self.f_expected(x0, 0, u)
        for x, point in ((x0, "the operating point"), (xp, "the operating point's prediction f(x0)")):
            for i, s in enumerate(self.sensors):
                for what, fn in (("h", self.h), ("the Jacobian dh/dx", self.H), ("the Hessians of h", self.h_hessian)):
                    if not np.all(np.isfinite(fn(i, x, 1))):
                        raise InputError(f"sensor {s.name!r}: {what} is not finite at {point} {where(x)} (step 1), "
                                         "where the filters and the design linearise it; is the sensor placed "
                                         "exactly at that point?")

    def with_stacked_sensors(self, name: str = "all") -> "Model":
        """The same model with one sensor that stacks every sensor (a centralized observer).

        Requires Gaussian measurement noises (their block-diagonal joint is Gaussian).
        """
        from scipy.linalg import block_diag

        from .noise import Gaussian

        if not all(isinstance(s.noise, Gaussian) for s in self.sensors):
            raise InputError("stacking sensors needs Gaussian measurement noise at every sensor")
        noise = Gaussian(np.concatenate([s.noise.mean for s in self.sensors]),
                         block_diag(*[s.noise.cov for s in self.sensors]))
        h = ca.vertcat(*[s.h for s in self.sensors])
        offsets = self._offsets
        angles = tuple(int(offsets[i] + a) for i, s in enumerate(self.sensors) for a in s.angles)
        with warnings.catch_warnings():  # its sensors' undeclared angles were named when this model was built
            warnings.simplefilter("ignore", ModelWarning)
            return Model(f"{self.name} (stacked)", self.x, self.f_expr, [Sensor(name, h, noise, angles=angles)],
                         self.process_noise,
                         self.prior, k=self.k, u=self.u if self.n_u else None,
                         mode=self.mode if self.n_modes else None,
                         mode_probs=self.mode_probs, noise_gain=self.noise_gain, state_names=self.state_names,
                         position_index=self.position_index, velocity_index=self.velocity_index,
                         description=self.description)

    def __digest__(self) -> tuple:
        """What the model is, for :func:`designer.digest.content_digest`: the NumPy translations of ``f``
        and every ``h_i`` (the evaluated operations, constants to the last bit), the noises, the prior and
        every other number and name; the Jacobians and Hessians are derived from these."""
        sensors = tuple((s.name, fn.source, s.noise, s.position, s.angles) for s, fn in zip(self.sensors, self._np_h))
        return (self.name, self.description, self._np_f.source, sensors, self.process_noise, self.prior,
                self.noise_gain, self.mode_probs, self.n_u, self.state_names, self.position_index,
                self.velocity_index)

    @property
    def digest(self) -> str:
        """SHA-256 of the model's content (:meth:`__digest__`): equal for equal models in any process."""
        d = self.__dict__.get("_digest")
        if d is None:
            from .digest import content_digest

            d = self.__dict__["_digest"] = content_digest(self)
        return d

    def describe(self) -> dict:
        """A JSON-ready description of the model."""
        return {
            "name": self.name,
            "description": self.description,
            "n_x": self.n_x,
            "state_names": list(self.state_names),
            "n_u": self.n_u,
            "modes": None if self.mode_probs is None else self.mode_probs.tolist(),
            "sensors": [
                {"name": s.name, "dim": s.dim, "noise": s.noise.describe(),
                 "position": None if s.position is None else list(s.position), "angles": list(s.angles)}
                for s in self.sensors
            ],
            "process_noise": self.process_noise.describe(),
            "noise_gain": self.noise_gain.tolist(),
            "prior": self.prior.describe(),
        }

    def __repr__(self) -> str:
        return f"Model({self.name!r}, n_x={self.n_x}, sensors={self.n_sensors}, modes={self.n_modes})"

