"""Boundary checks shared by every layer.

Every check raises a subclass of ``ValueError`` whose message names the
offending parameter and the allowed range, so that the command line can turn
it into a one-line error (exit code 2).
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "CfdesignError",
    "CfdesignWarning",
    "ModelWarning",
    "InputError",
    "ComputationError",
    "NonFiniteError",
    "check_probability",
    "check_finite",
    "check_shape",
    "check_covariance",
    "check_positive",
    "check_int",
    "check_type",
    "check_bool",
    "check_path",
    "check_strings",
    "check_rng",
    "as_vector",
]


class CfdesignError(Exception):
    """Base class of every error the package raises on purpose."""


class InputError(CfdesignError, ValueError):
    """A parameter is outside its allowed range, has the wrong shape or type."""


class ComputationError(CfdesignError, RuntimeError):
    """A computation failed or is infeasible (CLI exit code 1)."""


class NonFiniteError(ComputationError):
    """A filter's numbers left finite numbers at ``step`` of row ``row`` of the runs it was given
    (a study names the filter and its own run: :func:`studies.pipeline.naming_filter`)."""

    def __init__(self, message: str, row: int, step: int):
        super().__init__(message)
        self.row, self.step = int(row), int(step)

    def __reduce__(self):  # keep the fields across processes and Dask
        return (NonFiniteError, (str(self), self.row, self.step))


class CfdesignWarning(UserWarning):
    """Base class of every warning the package gives on purpose (the command line prints it as one line,
    ``cfdesign: warning: ...``)."""


class ModelWarning(CfdesignWarning):
    """A model is accepted but probably not what its author meant (e.g. an atan2 bearing not declared an angle)."""


def _type_name(value) -> str:
    return "None" if value is None else type(value).__name__


def check_finite(name: str, value) -> np.ndarray:
    """Return ``value`` as a float array, rejecting NaN and infinity.

    Numbers and (nested sequences or arrays of) numbers only: ``None``, text (``"0.1"``,
    which NumPy would read as a number) and ragged nesting are refused with the type given.
    """
    if value is None or isinstance(value, (str, bytes)):
        raise InputError(f"{name} must be numeric, got " + ("None" if value is None else
                                                           f"{type(value).__name__} {value!r}"))
    try:
        if np.asarray(value).dtype.kind in "USV":  # text or raw bytes inside a sequence
            raise TypeError("it holds text")
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from None
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite (no NaN or inf)")
    return arr


def check_shape(name: str, value, shape: tuple) -> np.ndarray:
    """Finite float array of exactly ``shape`` (``None`` entries match any size)."""
    arr = check_finite(name, value)
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def as_vector(name: str, value, dim: int | None = None) -> np.ndarray:
    """Finite 1-D float vector, of length ``dim`` when given (scalars allowed for dim 1)."""
    arr = check_finite(name, value)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise InputError(f"{name} must be a vector, got shape {arr.shape}")
    if dim is not None and arr.shape[0] != dim:
        raise InputError(f"{name} must have length {dim}, got {arr.shape[0]}")
    return arr


def check_covariance(name: str, value, dim: int | None = None, *, semidefinite: bool = False) -> np.ndarray:
    """Symmetric positive-definite (or semidefinite) ``dim x dim`` matrix.

    A scalar is accepted for ``dim == 1``; a vector is *not* taken as a diagonal
    so that a mistaken shape is never silently reinterpreted.
    """
    arr = check_finite(name, value)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        raise InputError(f"{name} must be a square matrix, got shape {arr.shape}")
    if dim is not None and arr.shape[0] != dim:
        raise InputError(f"{name} must be {dim}x{dim}, got {arr.shape[0]}x{arr.shape[1]}")
    scale = max(1.0, float(np.max(np.abs(arr))))
    if not np.allclose(arr, arr.T, rtol=0.0, atol=1e-12 * scale):
        raise InputError(f"{name} must be symmetric")
    arr = 0.5 * (arr + arr.T)
    eig_min = float(np.linalg.eigvalsh(arr)[0])
    if semidefinite:
        if eig_min < -1e-12 * scale:
            raise InputError(f"{name} must be positive semidefinite (smallest eigenvalue {eig_min:.3g} < 0)")
    elif eig_min <= 0.0:
        raise InputError(f"{name} must be positive definite (smallest eigenvalue {eig_min:.3g} <= 0)")
    return arr


def check_probability(name: str, value, *, open_upper: bool = False) -> np.ndarray:
    """Probabilities in [0, 1] (or [0, 1) with ``open_upper``)."""
    arr = check_finite(name, value)
    bad = (arr < 0.0) | ((arr >= 1.0) if open_upper else (arr > 1.0))
    if np.any(bad):
        rng = "[0, 1)" if open_upper else "[0, 1]"
        raise InputError(f"{name} must lie in {rng}, got {arr[bad].ravel()[0]!r}")
    return arr


def check_int(name: str, value, minimum: int, maximum: int | None = None) -> int:
    """An integer (not a bool) ``>= minimum`` (and ``<= maximum`` when given)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum \
            or (maximum is not None and value > maximum):
        allowed = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise InputError(f"{name} must be an integer {allowed}, got {value!r}")
    return int(value)


def check_type(name: str, value, types: type | tuple[type, ...], what: str, *, optional: bool = False):
    """``value`` when it is an instance of ``types`` (or None with ``optional``), else InputError naming ``name``
    and ``what`` it must be (``"a designer.SensorNetwork"``)."""
    if (optional and value is None) or (isinstance(value, types) and not (isinstance(value, bool)
                                                                          and bool not in _as_tuple(types))):
        return value
    raise InputError(f"{name} must be {what}{' or None' if optional else ''}, got {_type_name(value)}")


def _as_tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def check_bool(name: str, value) -> bool:
    """``True`` or ``False`` (NumPy's too), nothing that merely converts to one (``"no"`` is true in Python)."""
    return bool(check_type(name, value, (bool, np.bool_), "True or False"))


def check_path(name: str, value, *, optional: bool = False):
    """A path (``str`` or ``os.PathLike``) as given (or None with ``optional``), else InputError."""
    import os

    return check_type(name, value, (str, os.PathLike), "a path (str or pathlib.Path)", optional=optional)


def check_strings(name: str, value, what: str = "strings") -> tuple[str, ...]:
    """A list or tuple of ``str`` (one string alone is refused: its characters would be taken one by one)."""
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        bad = next((v for v in value if not isinstance(v, str)), None) if isinstance(value, (list, tuple)) else None
        got = _type_name(value) if not isinstance(value, (list, tuple)) else f"an item {bad!r}"
        raise InputError(f"{name} must be a list of {what}, got {got}")
    return tuple(value)


def check_rng(rng) -> np.random.Generator:
    """The explicit random generator every sampling function takes."""
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return rng


def check_positive(name: str, value, *, strict: bool = True) -> np.ndarray:
    """Positive (or non-negative) finite values."""
    arr = check_finite(name, value)
    bad = (arr <= 0.0) if strict else (arr < 0.0)
    if np.any(bad):
        rel = "> 0" if strict else ">= 0"
        raise InputError(f"{name} must be {rel}, got {arr[bad].ravel()[0]!r}")
    return arr
