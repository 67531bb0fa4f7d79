"""Code generation of the fused kernels: a model's propagation, weights and likelihood pieces as Python source.

From the model's CasADi functions (:func:`designer.jit.scalar_statements`, the
instruction walk of :mod:`designer.codegen`) this module writes small functions over a
**block** of particles, with the model's constants inlined: the propagation (``f`` plus
the process noise ``G (mean + L z)``, ``G L`` inlined), the weights with the weighted
mean, and the pieces every likelihood family uses (a Gaussian or mixture density's
log terms, the log-sum-exp split into its largest term and the others).  The families
(:mod:`filters.fused.packets`, ...) generate their likelihoods with them.  Each function
is compiled by :func:`compile_kernel`: written as a module of the kernel cache
(``<cache>/kernels``, :func:`kernel_paths` lists a model's) and compiled with numba's
on-disk cache, so a later process loads it instead of compiling.

The kernels split each block into loops that LLVM vectorises (the likelihood when ``h``
has no branch or call, the exps) and loops that must stay scalar (the generator's draws,
:mod:`filters.fused.streams`, and the sums of the weights).  Measured on target-range-bearing
(Round-Robin, 500 particles, one thread): about 31 ns per particle-step, of which the four
normal draws are about 10.
"""
from __future__ import annotations

import re
import weakref
from pathlib import Path

import numpy as np
from numba.core import types

from designer.jit import compile_source, scalar_statements
from designer.model import Model
from designer.noise import Gaussian, GaussianMixture, Noise
from designer.validation import InputError

from .cache import FAST, STAMP
from .driver import PROP_T, WEIGH_T
from .primitives import exp_nonpos, logaddexp, ndtr, wrap_angle
from .streams import draw_normals, draw_uniforms, keep, load, normal

__all__ = ["LOG_2PI", "model_kernels", "kernel_paths", "const", "compile_kernel", "noise_terms", "propagation",
           "propagation_predrawn", "weights", "components", "component_lines", "max_others_lines", "shared_bodies",
           "split_powers"]

LOG_2PI = float(np.log(2.0 * np.pi))
_KERNELS: "weakref.WeakKeyDictionary[Model, dict]" = weakref.WeakKeyDictionary()
# The helpers the generated code calls by these names (besides designer.jit's).
_NS = {"ndtr": ndtr, "_exp": exp_nonpos, "_wrap": wrap_angle, "_logaddexp": logaddexp, "_load": load, "_keep": keep,
       "_normal": normal, "_normals": draw_normals, "_uniforms": draw_uniforms}


def model_kernels(model: Model) -> dict:
    """This process's compiled kernels of ``model`` by key (kept as long as the model object lives)."""
    d = _KERNELS.get(model)
    if d is None:
        d = _KERNELS[model] = {}
    return d


def const(v: float) -> str:
    """Source of a finite float constant (exact: ``repr`` round-trips)."""
    return repr(float(v))


def compile_kernel(model: Model, key, src: str, fname: str, what: str, ftype, helpers: dict | None = None):
    """``fname`` of ``src`` (generated for ``model``) compiled for the function type ``ftype``, kept per model.

    The source becomes a module of the kernel cache and its compiled code is cached on
    disk (:func:`designer.jit.compile_source`): a later process loads it.  The source's
    path is recorded (:func:`kernel_paths`).  Returned as a first-class function value
    (numba's wrapper address protocol) rather than a dispatcher: passing it to the
    drivers then costs no signature lookup per call.  ``helpers``: the functions the source calls besides the
    shared ones (compiled, cached numba functions of the family's module).
    """
    cache = model_kernels(model)
    if key not in cache:
        fn = compile_source(src, fname, f"{what} of {model.name!r}", {**_NS, **(helpers or {})}, stamp=STAMP,
                            fastmath=FAST)
        sig = ftype.signature
        fn.compile(sig)
        cache[key] = types.CompileResultWAP(fn.overloads[tuple(sig.args)])
        _PATHS.setdefault(model, {})[str(key)] = Path(fn.path)
    return cache[key]


_PATHS: "weakref.WeakKeyDictionary[Model, dict]" = weakref.WeakKeyDictionary()


def kernel_paths(model: Model) -> dict[str, Path]:
    """The generated source files of ``model``'s kernels compiled in this process, by kernel key.

    Keys: ``'prop'`` (the propagation), ``'weigh'`` (the weights), the likelihoods'
    ``"('lik', (family, variant...))"``.

    The files are modules in ``<cache>/kernels`` (:func:`designer.jitcache.kernels_dir`),
    named ``<what> of '<model name>'-<key>.py``: readable Python, the model's ``f`` and
    ``h`` translated statement by statement, with the noise constants inlined.
    """
    if not isinstance(model, Model):
        raise InputError(f"model must be a designer.Model, got {type(model).__name__}")
    return dict(_PATHS.get(model, {}))


def noise_terms(model: Model, comp: Gaussian, z: str) -> list[str]:
    """Per state component ``i``, the source of ``(G (mean + L z))_i`` for the Gaussian ``comp`` (constants inlined)."""
    G = model.noise_gain
    gm, GL = G @ comp.mean, G @ comp._chol
    out = []
    for i in range(model.n_x):
        noise_i = " + ".join(f"{const(GL[i, j])} * {z}{j}" for j in range(GL.shape[1]) if GL[i, j] != 0.0) or "0.0"
        out.append(noise_i if gm[i] == 0.0 else f"{const(gm[i])} + ({noise_i})")
    return out


def propagation(model: Model):
    """``prop(X, anc, XN, m0, n, k, rng, buf)``: ``XN[m] = f(X[anc[m]], k) + G (mean + L z)``, ``z ~ N(0, I)``,
    for ``m = m0 .. m0 + n − 1``: one particle's ``n_w`` normals in a row, particle after particle (NumPy's
    order), drawn as it goes (``buf`` unused: ``nd = 0``)."""
    if "prop" in model_kernels(model):  # generating the source costs more than the lookup
        return model_kernels(model)["prop"]
    noise = model.process_noise
    if not isinstance(noise, Gaussian):
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; "
                         "the fused kernels need Gaussian process noise")
    lines = ["def prop(X, anc, XN, m0, n, k, rng, buf):",
             "    S, h, l = _load(rng)  # the generator's state in registers", "    for m in range(m0, m0 + n):",
             "        a = anc[m]"]
    lines += scalar_statements(model.casadi_f, ["X[a, {}]", "k", None, None], "f{}", indent="        ")
    # one copy of the sampler per normal: drawn in a loop into a scratch array, the same numbers compile 0.6 s
    # faster, but LLVM then fuses the noise terms otherwise (results move in the last bits)
    lines += [f"        z{j}, h, l = _normal(S, h, l)" for j in range(noise.dim)]
    lines += [f"        XN[m, {i}] = f{i} + ({t})" for i, t in enumerate(noise_terms(model, noise, "z"))]
    lines.append("    _keep(rng, h, l)")
    return compile_kernel(model, "prop", "\n".join(lines), "prop", "the propagation", PROP_T)


def choice_count(u: str, probs) -> str:
    """Source of ``Generator.choice(len(probs), p=probs)`` given its uniform ``u``: NumPy's
    ``searchsorted(cdf, u, 'right')`` with ``cdf = cumsum(p) / sum(p)``, i.e. the number of ``cdf`` entries
    ``<= u`` (the last, 1, never is)."""
    cdf = np.cumsum(np.asarray(probs, dtype=np.float64))
    cdf /= cdf[-1]
    return " + ".join(["0"] + [f"({u} >= {const(c)})" for c in cdf[:-1]])


def propagation_predrawn(model: Model) -> tuple:
    """``(prop, nd)``: the propagation of a model with switching modes and/or Gaussian-mixture process noise.

    It draws as :func:`filters.particle.transition_proposal` does, in blocks per step:
    ``M`` uniforms for the modes (``Generator.choice`` with ``model.mode_probs``), ``M``
    uniforms for the mixture's components (``GaussianMixture.sample``: ``choice`` with
    its weights), then ``M n_w`` standard normals, particle after particle.  These
    ``nd`` numbers per particle are drawn into ``buf`` at the step's first block
    (``m0 = 0``, see :func:`_step`), then ``XN[m] = f(X[anc[m]], k, mode) + G (mean_c +
    L_c z)`` with the particle's mode and component ``c``.  A model without modes and
    with Gaussian noise gets :func:`propagation` (``nd = 0``), which draws as it goes.
    """
    noise = model.process_noise
    if not model.n_modes and isinstance(noise, Gaussian):
        return propagation(model), 0
    if isinstance(noise, Gaussian):
        comps, weights = [noise], None
    elif isinstance(noise, GaussianMixture):
        comps, weights = list(noise.components), noise.weights
    else:
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; the fused kernels "
                         "support Gaussian and GaussianMixture process noise")
    n_w = noise.dim
    nu = int(model.n_modes > 0) + int(weights is not None)  # blocks of M uniforms: the modes', the labels'
    nd = nu + n_w
    cache = model_kernels(model)
    if "prop_predrawn" in cache:
        return cache["prop_predrawn"], nd
    lines = ["def prop(X, anc, XN, m0, n, k, rng, buf):", "    M = X.shape[0]", f"    zo = {nu} * M",
             "    if m0 == 0:  # the whole step's draws, in NumPy's order"]
    lines += [f"        _uniforms(rng, buf, {b} * M, M)" for b in range(nu)]
    lines += [f"        _normals(rng, buf, zo, M * {n_w})", "    for m in range(m0, m0 + n):", "        a = anc[m]"]
    if model.n_modes:
        lines.append(f"        md = float({choice_count('buf[m]', model.mode_probs)})")
    lines += scalar_statements(model.casadi_f, ["X[a, {}]", "k", None, "md" if model.n_modes else None], "f{}",
                               indent="        ")
    lines += [f"        z{j} = buf[zo + m * {n_w} + {j}]" for j in range(n_w)]
    terms = [noise_terms(model, g, "z") for g in comps]
    if weights is not None:
        lines.append(f"        lab = {choice_count(f'buf[{nu - 1} * M + m]', weights)}")
    for i in range(model.n_x):
        sel = terms[-1][i]
        for c in range(len(comps) - 2, -1, -1):
            sel = f"({terms[c][i]}) if lab == {c} else ({sel})"
        lines.append(f"        XN[m, {i}] = f{i} + ({sel})")
    return compile_kernel(model, "prop_predrawn", "\n".join(lines), "prop", "the propagation", PROP_T), nd


def weights(model: Model):
    """``weigh(x, b, s, best, W, mean) -> (Σ W, Σ W²)``: ``W = exp(b - best) s`` and the weighted mean.

    Generated per state dimension so that the mean's sums are local scalars; the
    exps in a loop of their own, which vectorises.
    """
    if "weigh" in model_kernels(model):
        return model_kernels(model)["weigh"]
    n = model.n_x
    lines = ["def weigh(x, b, s, best, W, mean):", "    M = x.shape[0]", "    for m in range(M):",
             "        W[m] = _exp(b[m] - best) * s[m]", "    acc = 0.0", "    s2 = 0.0"]
    lines += [f"    a{i} = 0.0" for i in range(n)]
    lines += ["    for m in range(M):", "        e = W[m]", "        acc += e", "        s2 += e * e"]
    lines += [f"        a{i} += e * x[m, {i}]" for i in range(n)]
    lines.append("    inv = 1.0 / acc")
    lines += [f"    mean[{i}] = a{i} * inv" for i in range(n)]
    lines.append("    return acc, s2")
    return compile_kernel(model, "weigh", "\n".join(lines), "weigh", "the weights", WEIGH_T)


def components(noise: Noise, label: str) -> list:
    if isinstance(noise, Gaussian):
        return [(None, noise)]
    if isinstance(noise, GaussianMixture):
        return [(w, g) for w, g in zip(noise.weights, noise.components) if w > 0.0]
    raise InputError(f"{label} noise is {type(noise).__name__}; the fused kernels support Gaussian and "
                     "GaussianMixture")


def component_lines(comps: list, r: list[str], indent: str) -> list[str]:
    """Statements setting ``t{c} = log w_c + log N(r; mean_c, cov_c)`` (as Gaussian.logpdf), constants inlined."""
    out = []
    d = len(r)
    for c, (w, g) in enumerate(comps):
        dv = []
        for j in range(d):
            if g.mean[j] == 0.0:
                dv.append(r[j])
            else:
                out.append(f"{indent}d{j} = {r[j]} - {const(g.mean[j])}")
                dv.append(f"d{j}")
        L = g._chol_inv  # lower triangular: z = L (r - mean)
        for i in range(d):
            t = [f"{const(L[i, j])} * {dv[j]}" for j in range(i + 1) if L[i, j] != 0.0]
            out.append(f"{indent}e{i} = {' + '.join(t) if t else '0.0'}")
        quad = " + ".join(f"e{i} * e{i}" for i in range(d))
        lp = f"-0.5 * ({const(d * LOG_2PI + g._logdet)} + ({quad}))"
        out.append(f"{indent}t{c} = {lp}" if w is None else f"{indent}t{c} = {const(np.log(w))} + ({lp})")
    return out


def max_others_lines(terms: list[str], ne: int, indent: str) -> list[str]:
    """Statements adding ``mx = max(terms)`` to ``b[m]`` and writing the others minus it into the ``ne`` slots.

    ``log Σ exp(terms) = mx + log(1 + Σ exp(slots))``.  The maximum is kept by
    selects (no data-dependent branch); slots past ``len(terms) - 1`` get ``-inf``.
    A NaN term ends up in ``mx`` or in a slot, so the log-likelihood is NaN (zero
    weight) as with ``logaddexp``; all terms ``-inf`` give ``mx = -inf``.
    """
    out = [f"{indent}mx = {terms[0]}"]
    for i, t in enumerate(terms[1:]):
        out += [f"{indent}u = {t}", f"{indent}o{i} = mx if u > mx else u", f"{indent}mx = u if u > mx else mx"]
    slots = [f"o{i} - mx" for i in range(len(terms) - 1)] + ["-_m.inf"] * (ne - len(terms) + 1)
    out += [f"{indent}x{i}[mm] = {v}" for i, v in enumerate(slots)]
    out.append(f"{indent}bb[mm] += mx")
    return out


_FLOAT = re.compile(r"(?<![\w.])(?:\d+\.\d*(?:e[+-]?\d+)?|\d+e[+-]?\d+)")  # a float literal (repr), not an index


def shared_bodies(bodies: list[str]) -> list[tuple[list[int], str, np.ndarray]]:
    """Sensors whose generated bodies differ only in float literals (e.g. sensor positions) share one body.

    Returns ``(members, body, table)`` per group: in ``body`` the literals that differ
    between the members read ``c0, c1, ...``, which row ``s`` of ``table`` holds for
    member ``s``.  Fewer, not more, loops to compile for a network of alike sensors.
    """
    groups: dict[str, list[int]] = {}
    for s, body in enumerate(bodies):
        groups.setdefault(_FLOAT.sub("#", body), []).append(s)
    out = []
    for members in groups.values():
        values = np.array([[float(v) for v in _FLOAT.findall(bodies[s])] for s in members]).reshape(len(members), -1)
        varies = np.flatnonzero(np.any(values != values[:1], axis=0))
        table = np.zeros((len(bodies), len(varies)))
        table[members] = values[:, varies]
        slot = {int(i): j for j, i in enumerate(varies)}
        count = iter(range(values.shape[1]))

        def literal(match, slot=slot, count=count):
            i = next(count)
            return f"c{slot[i]}" if i in slot else match.group(0)

        out.append((members, _FLOAT.sub(literal, bodies[members[0]]), table))
    return out


_POW_LINE = re.compile(r"^(\s*)(w\d+) = (w\d+) \*\* (w\d+)$")  # designer.jit's POW / CONSTPOW template
_ASSIGN = re.compile(r"^\s*(\w+) = (.*)$")
_REGISTER = re.compile(r"\bw\d+\b")


def split_powers(lines: list[str]) -> tuple[list[str], list[str], int] | None:
    """The powers of generated statements (:func:`designer.jit.scalar_statements`) taken out of their loop.

    Returns ``(first, second, J)``: ``first`` is ``lines`` with the ``j``-th power
    ``w = a ** b`` replaced by ``PA[j, m] = a``, ``PB[j, m] = b`` (and ``w = 1.0``), ``second``
    with it replaced by ``w = PR[j, m]``; between the two loops,
    ``primitives.vpow_rows(PA, PB, PR, n)`` takes every power in one loop that vectorises
    (libm's ``pow`` is a call per particle).  ``None`` when there is no power or when a
    power's operand depends on another power's result (the first loop could not compute it).
    """
    first, second, tainted, J = [], [], set(), 0
    for line in lines:
        p = _POW_LINE.match(line)
        if p:
            ind, w, a, b = p.groups()
            if {a, b} & tainted:
                return None
            first += [f"{ind}PA[{J}, m] = {a}", f"{ind}PB[{J}, m] = {b}", f"{ind}{w} = 1.0"]
            second.append(f"{ind}{w} = PR[{J}, m]")
            tainted.add(w)
            J += 1
            continue
        first.append(line)
        second.append(line)
        a = _ASSIGN.match(line)
        if a:
            lhs, rhs = a.groups()
            if set(_REGISTER.findall(rhs)) & tainted:
                tainted.add(lhs)
            else:
                tainted.discard(lhs)
    return (first, second, J) if J else None
