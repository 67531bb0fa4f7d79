"""Noise distributions with batched densities and explicit random generators.

Every distribution is an immutable value over vectors of dimension ``dim``:
``logpdf(x)`` and ``pdf(x)`` take ``x`` of shape ``(..., dim)`` and return shape
``(...)``; ``cdf(x)`` is the joint distribution function P(X <= x) where it has a
closed form (independent components, or one dimension); ``sample(rng, shape)``
returns ``shape + (dim,)`` and draws only from the ``numpy.random.Generator``
passed in.  ``mean`` and ``cov`` are the exact first two moments.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .validation import (InputError, as_vector, check_covariance, check_finite, check_positive, check_probability,
                         check_rng)

__all__ = [
    "Noise", "Gaussian", "GaussianMixture", "TruncatedGaussian", "UniformBox", "PolarVelocityPrior", "spawn_generators",
    "logsumexp",
]

_LOG_2PI = float(np.log(2.0 * np.pi))


def spawn_generators(seed: int | np.random.SeedSequence, n: int) -> list[np.random.Generator]:
    """Independent generators for ``n`` Monte Carlo runs from one seed (``SeedSequence.spawn``)."""
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    return [np.random.default_rng(child) for child in ss.spawn(n)]


def logsumexp(a, axis: int) -> np.ndarray:
    """``log Σ exp(a)`` along ``axis`` of a real array: the numbers of ``scipy.special.logsumexp(a, axis=axis)``.

    The same floating-point operations in the same order as SciPy's for real input (the largest
    term counted apart, ``log1p`` of the others' sum scaled by the count of largest terms, the
    plain ``log Σ exp`` where that is not finite), so the results are SciPy's to the bit; without
    its array-API layer, which costs about ten times the arithmetic on the particle filters'
    stacks.
    """
    a = np.asarray(a, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        fallback = np.log(np.sum(np.exp(a), axis=axis, keepdims=True))
        a_max = np.max(a, axis=axis, keepdims=True)
        top = a == a_max
        m = np.sum(top.astype(float), axis=axis, keepdims=True)
        s = np.sum(np.exp(np.where(top, -np.inf, a) - a_max), axis=axis, keepdims=True)
        s = np.where(s == 0, s, s / m)
        negative = np.sign(s + 1) * np.sign(m) < 0
        s = np.where(s < -1, -s - 2, s)
        out = np.log1p(s) + np.log(np.abs(m)) + a_max
        out[negative] = np.nan
    out = np.squeeze(np.where(np.isfinite(out), out, fallback), axis=axis)
    return out[()] if out.ndim == 0 else out


def _shape(shape) -> tuple[int, ...]:
    if shape is None:
        return ()
    if isinstance(shape, (int, np.integer)):
        return (int(shape),)
    return tuple(int(s) for s in shape)


def _points(x, dim: int) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if dim == 1 and (arr.ndim == 0 or arr.shape[-1] != 1):
        arr = arr[..., None]
    if arr.ndim == 0 or arr.shape[-1] != dim:
        raise InputError(f"x must have last dimension {dim}, got shape {arr.shape}")
    return arr


def _bound(name: str, value, d: int) -> np.ndarray:
    """Truncation bound: scalar or length-``d`` vector; +-inf allowed, NaN not."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from None
    if arr.ndim == 0:
        arr = np.full(d, float(arr))
    if arr.shape != (d,):
        raise InputError(f"{name} must be a scalar or have length {d}, got shape {arr.shape}")
    return arr


class Noise:
    """Common interface; subclasses define ``dim``, ``mean``, ``cov``, ``logpdf``, ``sample``."""

    dim: int

    def pdf(self, x) -> np.ndarray:
        return np.exp(self.logpdf(x))

    def cdf(self, x) -> np.ndarray:  # pragma: no cover - overridden where defined
        raise NotImplementedError(f"{type(self).__name__} has no closed-form joint CDF")

    def describe(self) -> dict:
        return {"type": type(self).__name__, "mean": self.mean.tolist(), "cov": self.cov.tolist()}


@dataclass(frozen=True, eq=False)
class Gaussian(Noise):
    """Multivariate normal N(mean, cov) with a Cholesky factor computed once."""

    mean: np.ndarray
    cov: np.ndarray
    _chol: np.ndarray = field(init=False, repr=False)
    _chol_inv: np.ndarray = field(init=False, repr=False)
    _logdet: float = field(init=False, repr=False)

    def __post_init__(self):
        mean = as_vector("mean", self.mean)
        cov = check_covariance("cov", self.cov, mean.shape[0])
        chol = np.linalg.cholesky(cov)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "_chol", chol)
        object.__setattr__(self, "_chol_inv", np.linalg.inv(chol))  # triangular, well conditioned by check
        object.__setattr__(self, "_logdet", 2.0 * float(np.sum(np.log(np.diag(chol)))))

    @classmethod
    def zero_mean(cls, cov) -> "Gaussian":
        cov = np.atleast_2d(check_finite("cov", cov))
        return cls(np.zeros(cov.shape[0]), cov)

    @property
    def dim(self) -> int:
        return self.mean.shape[0]

    def logpdf(self, x) -> np.ndarray:
        z = (_points(x, self.dim) - self.mean) @ self._chol_inv.T
        return -0.5 * (self.dim * _LOG_2PI + self._logdet + np.einsum("...i,...i->...", z, z))

    def cdf(self, x) -> np.ndarray:
        from scipy import special

        x = _points(x, self.dim)
        sd = np.sqrt(np.diag(self.cov))
        if self.dim == 1 or np.count_nonzero(self.cov - np.diag(np.diag(self.cov))) == 0:
            return np.prod(special.ndtr((x - self.mean) / sd), axis=-1)
        from scipy import stats  # the correlated case only: scipy.stats takes most of a second to import

        flat = x.reshape(-1, self.dim)
        vals = stats.multivariate_normal(self.mean, self.cov).cdf(flat)
        return np.asarray(vals, dtype=float).reshape(x.shape[:-1])

    def sample(self, rng: np.random.Generator, shape=()) -> np.ndarray:
        z = check_rng(rng).standard_normal(_shape(shape) + (self.dim,))
        return self.mean + z @ self._chol.T


@dataclass(frozen=True, eq=False)
class GaussianMixture(Noise):
    """Finite mixture sum_c w_c N(mean_c, cov_c), e.g. glint noise."""

    weights: np.ndarray
    components: tuple[Gaussian, ...]
    _cdf: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        comps = tuple(self.components) if isinstance(self.components, (list, tuple)) else ()
        if not comps or not all(isinstance(c, Gaussian) for c in comps):
            raise InputError("components must be a non-empty sequence of Gaussian")
        if len({c.dim for c in comps}) != 1:
            raise InputError("components must all have the same dimension")
        w = check_probability("weights", as_vector("weights", self.weights, len(comps)))
        if abs(w.sum() - 1.0) > 1e-9:
            raise InputError(f"weights must sum to 1, got {w.sum():.12g}")
        object.__setattr__(self, "weights", w / w.sum())
        object.__setattr__(self, "components", comps)
        cdf = self.weights.cumsum()  # what Generator.choice(p=weights) searches, computed once
        object.__setattr__(self, "_cdf", cdf / cdf[-1])

    @classmethod
    def from_arrays(cls, weights: Sequence[float], means, covs) -> "GaussianMixture":
        return cls(np.asarray(weights, float), tuple(Gaussian(m, c) for m, c in zip(means, covs)))

    @property
    def dim(self) -> int:
        return self.components[0].dim

    @property
    def mean(self) -> np.ndarray:
        return sum(w * c.mean for w, c in zip(self.weights, self.components))

    @property
    def cov(self) -> np.ndarray:
        m = self.mean
        second = sum(w * (c.cov + np.outer(c.mean, c.mean)) for w, c in zip(self.weights, self.components))
        return second - np.outer(m, m)

    def logpdf(self, x) -> np.ndarray:
        with np.errstate(divide="ignore"):
            logw = np.log(self.weights)
        terms = np.stack([lw + c.logpdf(x) for lw, c in zip(logw, self.components)], axis=0)
        return logsumexp(terms, axis=0)

    def cdf(self, x) -> np.ndarray:
        return sum(w * c.cdf(x) for w, c in zip(self.weights, self.components))

    def sample(self, rng: np.random.Generator, shape=()) -> np.ndarray:
        shape = _shape(shape)
        rng = check_rng(rng)
        # The labels of ``rng.choice(len(components), size=shape, p=weights)``, draw for draw (NumPy's own
        # steps: one uniform per label against the normalised cumulative weights), without its checks of p.
        labels = self._cdf.searchsorted(rng.random(shape), side="right")
        z = rng.standard_normal(shape + (self.dim,))
        if not shape:  # one draw (a simulation step): its component alone, with the same product as below
            comp = self.components[int(labels)]
            return comp.mean + (z[None] @ comp._chol.T)[0]
        out = np.empty(shape + (self.dim,))
        for c, comp in enumerate(self.components):
            sel = labels == c
            out[sel] = comp.mean + z[sel] @ comp._chol.T
        return out

    def describe(self) -> dict:
        return {
            "type": "GaussianMixture",
            "weights": self.weights.tolist(),
            "means": [c.mean.tolist() for c in self.components],
            "covs": [c.cov.tolist() for c in self.components],
        }


@dataclass(frozen=True, eq=False)
class TruncatedGaussian(Noise):
    """Independent components, each N(loc, scale^2) truncated to [lower, upper].

    ``loc`` and ``scale`` are those of the parent (untruncated) normal; the
    bounds are absolute.  ``mean`` and ``cov`` are the truncated moments.
    """

    loc: np.ndarray
    scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    _dist: object = field(init=False, repr=False, default=None)

    def __post_init__(self):
        from scipy import special

        loc = as_vector("loc", self.loc)
        d = loc.shape[0]
        scale = check_positive("scale", as_vector("scale", self.scale, d))
        lower, upper = (_bound(name, getattr(self, name), d) for name in ("lower", "upper"))
        if np.any(np.isnan(lower)) or np.any(np.isnan(upper)) or np.any(lower >= upper):
            raise InputError("lower must be < upper for every component of the truncated Gaussian")
        object.__setattr__(self, "loc", loc)
        object.__setattr__(self, "scale", scale)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        a, b = (lower - loc) / scale, (upper - loc) / scale
        # Mass of the parent normal on [a, b], from the tail nearer to the interval (no cancellation).
        upper_side = a > 0
        mass = np.where(upper_side, special.ndtr(-a) - special.ndtr(-b), special.ndtr(b) - special.ndtr(a))
        object.__setattr__(self, "_ab", (a, b, upper_side, mass))

    def _std(self, x) -> np.ndarray:
        return (_points(x, self.dim) - self.loc) / self.scale

    @property
    def dim(self) -> int:
        return self.loc.shape[0]

    def _truncnorm(self):
        """SciPy's truncated normal, for the moments only (densities and sampling are in closed form below); made
        on first use, as importing scipy.stats takes most of a second that a filter run does not need."""
        if self._dist is None:
            from scipy import stats

            a, b = (self.lower - self.loc) / self.scale, (self.upper - self.loc) / self.scale
            object.__setattr__(self, "_dist", stats.truncnorm(a, b, loc=self.loc, scale=self.scale))
        return self._dist

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self._truncnorm().mean(), dtype=float)

    @property
    def cov(self) -> np.ndarray:
        return np.diag(np.asarray(self._truncnorm().var(), dtype=float))

    def logpdf(self, x) -> np.ndarray:
        a, b, _, mass = self._ab
        z = self._std(x)
        lp = -0.5 * z * z - np.log(np.sqrt(2 * np.pi) * self.scale * mass)
        return np.sum(np.where((z >= a) & (z <= b), lp, -np.inf), axis=-1)

    def cdf(self, x) -> np.ndarray:
        from scipy import special

        a, b, upper_side, mass = self._ab
        z = self._std(x)
        F = np.where(upper_side, special.ndtr(-a) - special.ndtr(-z), special.ndtr(z) - special.ndtr(a)) / mass
        return np.prod(np.clip(F, 0.0, 1.0), axis=-1)

    def sample(self, rng: np.random.Generator, shape=()) -> np.ndarray:
        size = _shape(shape) + (self.dim,)
        from scipy import special

        # Inverse-CDF sampling from the generator passed in (one uniform per component).
        a, b, upper_side, mass = self._ab
        u = check_rng(rng).random(size)
        z = np.where(upper_side, -special.ndtri(special.ndtr(-a) - u * mass), special.ndtri(special.ndtr(a) + u * mass))
        return self.loc + self.scale * np.clip(z, a, b)

    def describe(self) -> dict:
        return {
            "type": "TruncatedGaussian",
            "loc": self.loc.tolist(),
            "scale": self.scale.tolist(),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
        }


@dataclass(frozen=True, eq=False)
class UniformBox(Noise):
    """Uniform distribution on the box [lower, upper] (deception signals)."""

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        lower = as_vector("lower", self.lower)
        upper = as_vector("upper", self.upper, lower.shape[0])
        if np.any(lower >= upper):
            raise InputError("lower must be < upper in every component of the uniform box")
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)

    @property
    def dim(self) -> int:
        return self.lower.shape[0]

    @property
    def mean(self) -> np.ndarray:
        return 0.5 * (self.lower + self.upper)

    @property
    def cov(self) -> np.ndarray:
        return np.diag((self.upper - self.lower) ** 2 / 12.0)

    def logpdf(self, x) -> np.ndarray:
        x = _points(x, self.dim)
        inside = np.all((x >= self.lower) & (x <= self.upper), axis=-1)
        return np.where(inside, -float(np.sum(np.log(self.upper - self.lower))), -np.inf)

    def cdf(self, x) -> np.ndarray:
        x = _points(x, self.dim)
        return np.prod(np.clip((x - self.lower) / (self.upper - self.lower), 0.0, 1.0), axis=-1)

    def sample(self, rng: np.random.Generator, shape=()) -> np.ndarray:
        return check_rng(rng).uniform(self.lower, self.upper, _shape(shape) + (self.dim,))

    def describe(self) -> dict:
        return {"type": "UniformBox", "lower": self.lower.tolist(), "upper": self.upper.tolist()}


@dataclass(frozen=True, eq=False)
class PolarVelocityPrior(Noise):
    """Prior of a constant-velocity state ``[px, vx, py, vy]`` given in polar velocity form.

    Position ~ N(position_mean, position_cov); independently speed ~ N(speed_mean,
    speed_std^2) and heading ~ N(heading_mean, heading_std^2) (radians from the
    x axis, on the real line), with ``vx = speed cos(heading)``,
    ``vy = speed sin(heading)`` (the prior of seed 002, after Dias and Bruno).
    The density sums every preimage ``(s, a)`` of a velocity (both signs of the
    speed, headings shifted by multiples of 2 pi) with the Jacobian ``1/|v|``.
    """

    position_mean: np.ndarray
    position_cov: np.ndarray
    speed_mean: float
    speed_std: float
    heading_mean: float
    heading_std: float
    _pos: Gaussian = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "_pos", Gaussian(as_vector("position_mean", self.position_mean, 2),
                                                  check_covariance("position_cov", self.position_cov, 2)))
        for name in ("speed_mean", "speed_std", "heading_mean", "heading_std"):
            object.__setattr__(self, name, float(as_vector(name, getattr(self, name), 1)[0]))
        check_positive("speed_std", self.speed_std)
        check_positive("heading_std", self.heading_std)

    dim = 4

    @property
    def mean(self) -> np.ndarray:
        c = np.exp(-0.5 * self.heading_std**2)
        vx = self.speed_mean * np.cos(self.heading_mean) * c
        vy = self.speed_mean * np.sin(self.heading_mean) * c
        m = self._pos.mean
        return np.array([m[0], vx, m[1], vy])

    @property
    def cov(self) -> np.ndarray:
        s2 = self.speed_mean**2 + self.speed_std**2  # E[s^2]
        mu, sd = self.heading_mean, self.heading_std
        e2 = np.exp(-2.0 * sd**2)
        ecc = 0.5 * (1.0 + np.cos(2 * mu) * e2)  # E[cos^2 a]
        ess = 0.5 * (1.0 - np.cos(2 * mu) * e2)
        esc = 0.5 * np.sin(2 * mu) * e2
        m = self.mean
        vel = np.array([[s2 * ecc, s2 * esc], [s2 * esc, s2 * ess]]) - np.outer(m[[1, 3]], m[[1, 3]])
        out = np.zeros((4, 4))
        out[np.ix_([0, 2], [0, 2])] = self._pos.cov
        out[np.ix_([1, 3], [1, 3])] = vel
        return out

    def logpdf(self, x) -> np.ndarray:
        from scipy import stats

        x = _points(x, 4)
        lp_pos = self._pos.logpdf(x[..., [0, 2]])
        r = np.hypot(x[..., 1], x[..., 3])
        phi = np.arctan2(x[..., 3], x[..., 1])
        # Heading preimages phi + shift + 2 pi n: centre n on the heading mean and
        # cover at least 8 heading standard deviations on either side.
        k = int(np.ceil(8.0 * float(self.heading_std) / (2 * np.pi))) + 1
        dens = 0.0
        for sign, shift in ((1.0, 0.0), (-1.0, np.pi)):
            base = phi + shift
            n0 = np.round((self.heading_mean - base) / (2 * np.pi))
            p_speed = stats.norm.pdf(sign * r, self.speed_mean, self.speed_std)
            for n in range(-k, k + 1):
                dens = dens + p_speed * stats.norm.pdf(
                    base + 2 * np.pi * (n0 + n), self.heading_mean, self.heading_std
                )
        with np.errstate(divide="ignore"):
            return lp_pos + np.log(dens) - np.log(r)

    def sample(self, rng: np.random.Generator, shape=()) -> np.ndarray:
        shape = _shape(shape)
        pos = self._pos.sample(check_rng(rng), shape)
        s = self.speed_mean + self.speed_std * rng.standard_normal(shape)
        a = self.heading_mean + self.heading_std * rng.standard_normal(shape)
        return np.stack([pos[..., 0], s * np.cos(a), pos[..., 1], s * np.sin(a)], axis=-1)

    def describe(self) -> dict:
        return {"type": "PolarVelocityPrior", "position_mean": self._pos.mean.tolist(),
                "position_cov": self._pos.cov.tolist(), "speed": [float(self.speed_mean), float(self.speed_std)],
                "heading": [float(self.heading_mean), float(self.heading_std)]}
