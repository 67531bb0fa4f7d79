"""The studies' figures: how they are made, drawn and written, in parallel where the platform forks.

A study's figure code (its ``figures(out, results, scenarios, arrays)``) builds bare
matplotlib figures with :func:`plotting` and hands each to :func:`save_figure`.
Drawing, not building, is what costs: a tenth of a second per figure of matplotlib's
Python code (the GIL: threads do not help), plus a quarter of a second to import
matplotlib, the largest fixed part of a small study.  So:

* :func:`png_tight` draws a figure once where ``savefig(bbox_inches="tight")`` draws it twice;
* inside :func:`figure_batch` (every study's outputs, :func:`studies.outputs.write_outputs`),
  :func:`save_figure` only records, and :func:`draw_figures` draws the batch over the
  usable cores: children forked from the process draw figures in turn, taking the next
  from a shared queue (a pipe of indices), while the process draws too;
* a study that writes outputs starts a :class:`FigureHelper` before it computes: a process
  forked then, which imports matplotlib (and draws a throwaway figure, loading the fonts)
  while the study computes, and draws the study's figures from its results when they
  arrive (pickled: the results and per-run arrays; the scenarios it already has).

Whoever draws a figure, the file is the same.  Every fork is a Linux-only path with a
serial fallback: a child or helper that fails or is killed costs time only, its figures
are then drawn by the calling process (which raises any error itself).
"""
from __future__ import annotations

import math
import os
import pickle
import signal
import struct
import sys
import textwrap
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from designer.fileio import atomic_write

from .feasibility_terms import FAILED, MAP_CATEGORIES, MAP_COLOURS, MAP_WORDS, map_category

__all__ = ["FIGURE_DPI", "plotting", "save_figure", "png_tight", "figure_batch", "draw_figures", "FigureHelper",
           "PALETTE", "filter_colours", "legend_beside", "trajectory_figure", "curves_figure", "tradeoff_figure",
           "TRADEOFF", "map_figure", "candidates_figure"]

FIGURE_DPI = 110
# One colour per filter in every figure of a study (:func:`filter_colours`): matplotlib's tab10 without its grey
# (kept, with black, for the truth, the sensors and references), then the lighter tab20 shades.
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf",
           "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5")
TRADEOFF = "fig_tradeoff.png"  # every study's summary figure: accuracy against cost and messages


class _Plotting:
    """The part of pyplot the studies' figures use, without pyplot: ``subplots`` makes a bare
    :class:`matplotlib.figure.Figure` (drawn with the Agg canvas), so a fresh study does not pay
    pyplot's import (about half a second) and no figure is kept in pyplot's global state."""

    def __init__(self):
        from matplotlib.patches import Rectangle

        self.Rectangle = Rectangle

    @staticmethod
    def subplots(nrows: int = 1, ncols: int = 1, *, figsize=None, layout: str | None = "constrained", **kw):
        """A figure, by default with constrained layout: a legend placed beside the axes (:func:`legend_beside`)
        gets room on the canvas, so the figure is still drawn once (:func:`png_tight`)."""
        from matplotlib.figure import Figure

        fig = Figure(figsize=figsize, layout=layout)
        return fig, fig.subplots(nrows, ncols, **kw)

    @staticmethod
    def close(fig) -> None:
        """Nothing to release: a bare figure is garbage once unreferenced."""


def plotting() -> _Plotting:
    """``subplots``, ``Rectangle`` and ``close`` as pyplot's (see :class:`_Plotting`)."""
    return _Plotting()


# ------------------------------------------------------------------------------------------- one figure
def png_tight(fig, fh, dpi: float = FIGURE_DPI) -> None:
    """``fig.savefig(fh, format="png", dpi=dpi, bbox_inches="tight")``, drawn once instead of twice.

    matplotlib's tight save draws the figure to measure its artists' extent, then draws it
    again on a canvas of that extent; here the figure is drawn once on its own canvas, and
    the pixels inside the extent (plus ``savefig.pad_inches``; padding beyond the canvas in
    the face colour) are written.  The same picture to within a pixel's offset (tested), in
    about two thirds of the time.  A figure with an artist reaching beyond its canvas is
    saved by matplotlib's own tight save, which widens the canvas.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.image import imsave

    own_dpi = fig.get_dpi()
    fig.set_dpi(dpi)
    try:
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        box = fig.get_tightbbox(canvas.get_renderer())  # inches
        pixels = np.asarray(canvas.buffer_rgba())  # rows from the top
    finally:
        fig.set_dpi(own_dpi)  # as savefig leaves it
    height, width = pixels.shape[:2]
    if box.x0 < 0 or box.y0 < 0 or box.x1 * dpi > width or box.y1 * dpi > height:
        fig.savefig(fh, format="png", dpi=dpi, bbox_inches="tight")
        return
    box = box.padded(matplotlib.rcParams["savefig.pad_inches"])
    x0, x1 = math.floor(box.x0 * dpi), math.ceil(box.x1 * dpi)
    y0, y1 = math.floor(box.y0 * dpi), math.ceil(box.y1 * dpi)  # from the bottom
    face = np.round(np.array(matplotlib.colors.to_rgba(fig.get_facecolor())) * 255).astype(np.uint8)
    out = np.empty((y1 - y0, x1 - x0, 4), np.uint8)
    out[...] = face
    top, left = max(0, height - y1), max(0, x0)
    part = pixels[top:height - max(0, y0), left:min(width, x1)]
    r0, c0 = top - (height - y1), left - x0
    out[r0:r0 + part.shape[0], c0:c0 + part.shape[1]] = part
    imsave(fh, out, format="png", dpi=dpi)


def _write(fig, path) -> None:
    atomic_write(path, lambda fh: png_tight(fig, fh))


_PENDING: ContextVar[list | None] = ContextVar("cfdesign_pending_figures", default=None)


def save_figure(fig, path: Path) -> None:
    """Write a figure (of :func:`plotting`'s ``subplots``) as PNG atomically (:func:`png_tight`).

    Inside :func:`figure_batch`, the figure is drawn when the batch ends, beside the others.
    """
    pending = _PENDING.get()
    if pending is not None:
        pending.append((fig, Path(path)))
    else:
        _write(fig, path)


# ------------------------------------------------------------------------------------------- many figures
@contextmanager
def figure_batch(processes: int | None = None):
    """Within it, :func:`save_figure` only records; when it ends without an exception, the figures are drawn by
    :func:`draw_figures` (over ``processes``, default every usable core)."""
    pending: list = []
    token = _PENDING.set(pending)
    try:
        yield
    finally:
        _PENDING.reset(token)
    draw_figures(pending, processes)


def _read_all(fd: int) -> bytes:
    chunks = []
    while True:
        b = os.read(fd, 1 << 16)
        if not b:
            return b"".join(chunks)
        chunks.append(b)


_QUEUE_BYTES = 65536  # a pipe's capacity on Linux: the queue is written whole before anyone reads it


def draw_figures(figures: Sequence[tuple], processes: int | None = None) -> None:
    """Write each ``(fig, path)`` as :func:`save_figure` does, over ``processes`` processes (default: every usable
    core).

    Where the platform forks (Linux), ``processes - 1`` children are forked (the figures are
    in their memory: nothing is serialised); they and this process take the figures' indices
    in turn from a pipe (reads of 4 bytes are atomic), so a slow figure does not hold up the
    rest, and each child reports the indices it wrote.  Any figure no child reported (a
    child failed or was killed) is drawn here afterwards.
    """
    from designer.cores import usable_cores

    from .runner import fork_worker

    figures = list(figures)
    n = min(len(figures), processes or usable_cores())
    if n <= 1 or not sys.platform.startswith("linux") or 4 * len(figures) > _QUEUE_BYTES:
        for fig, path in figures:
            _write(fig, path)
        return
    parent = os.getpid()
    queue_r, queue_w = os.pipe()
    os.write(queue_w, b"".join(struct.pack("<i", i) for i in range(len(figures))))  # fits: no reader needed yet
    os.close(queue_w)
    children = []
    try:
        for _ in range(n - 1):
            done_r, done_w = os.pipe()
            try:
                pid = fork_worker(parent)
            except OSError:  # no more processes: the ones there are draw the rest
                os.close(done_r)
                os.close(done_w)
                break
            if pid == 0:  # pragma: no cover - the child
                code = 1
                try:
                    os.close(done_r)
                    for i in _take(queue_r):
                        _write(*figures[i])
                        os.write(done_w, struct.pack("<i", i))
                    code = 0
                finally:
                    os._exit(code)
            os.close(done_w)
            children.append((pid, done_r))
        drawn = set()
        for i in _take(queue_r):
            _write(*figures[i])
            drawn.add(i)
    except BaseException:
        for pid, fd in children:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            os.close(fd)
        raise
    finally:
        os.close(queue_r)
    for pid, fd in children:
        done = _read_all(fd)
        os.close(fd)
        os.waitpid(pid, 0)
        drawn.update(struct.unpack(f"<{len(done) // 4}i", done[:len(done) // 4 * 4]))
    for i, (fig, path) in enumerate(figures):
        if i not in drawn:
            _write(fig, path)


def _read_exactly(fd: int, size: int) -> bytes:
    chunks, left = [], size
    while left:
        b = os.read(fd, min(left, 1 << 20))
        if not b:
            raise EOFError("the figures' sender stopped")
        chunks.append(b)
        left -= len(b)
    return b"".join(chunks)


def _take(fd: int):
    """The figure indices this process takes from the queue, until it is empty."""
    while True:
        b = os.read(fd, 4)
        if len(b) < 4:
            return
        yield struct.unpack("<i", b)[0]


# ------------------------------------------------------------------------------------------- a helper process
class FigureHelper:
    """A process that draws a study's figures, forked before the study computes.

    ``draw(out, results, arrays)`` (the study's figure function, bound to its scenarios) is
    called in the helper once :meth:`send` gives it the results; meanwhile the helper has
    imported matplotlib and drawn a throwaway figure, so neither the import nor the fonts'
    loading waits for the study.  Linux only (:meth:`start` gives None elsewhere).
    """

    def __init__(self, pid: int, job: int, done: int):
        self._pid, self._job, self._done = pid, job, done

    @classmethod
    def start(cls, draw: Callable[[Path, dict, Mapping], None]) -> "FigureHelper | None":
        from .runner import fork_worker

        if not sys.platform.startswith("linux"):
            return None
        parent = os.getpid()
        job_r, job_w = os.pipe()
        done_r, done_w = os.pipe()
        pid = fork_worker(parent)
        if pid == 0:  # pragma: no cover - the helper
            code = 1
            try:
                os.close(job_w)
                os.close(done_r)
                _warm_up(job_r)
                size = struct.unpack("<q", _read_exactly(job_r, 8))[0]
                if size > 0:
                    out, results, arrays = pickle.loads(_read_exactly(job_r, size))
                    with figure_batch():
                        draw(Path(out), results, arrays)
                    os.write(done_w, b"ok")
                code = 0
            finally:
                os._exit(code)
        os.close(job_r)
        os.close(done_w)
        return cls(pid, job_w, done_r)

    def send(self, out: Path, results: dict, arrays: Mapping) -> bool:
        """Give the helper the figures to draw into ``out`` and return at once (True if it has them): the caller
        may write its other files meanwhile, then :meth:`wait`."""
        if self._job is None:
            return False
        try:
            payload = pickle.dumps((str(out), results, arrays), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 - not picklable: the caller draws
            self.close()
            return False
        try:  # length first: processes forked later (a runner's workers) may hold this pipe's end open too
            for data in (struct.pack("<q", len(payload)), payload):
                view = memoryview(data)
                while view:
                    view = view[os.write(self._job, view):]
        except OSError:  # the helper is gone
            self.close()
            return False
        os.close(self._job)
        self._job = None
        return True

    def wait(self) -> bool:
        """Wait for the figures :meth:`send` gave; True when the helper wrote them all."""
        if self._done is None:
            return False
        ok = _read_all(self._done) == b"ok"
        self.close()
        return ok

    def close(self) -> None:
        """End the helper and reap it: killed if it was given nothing to draw (it may still be importing)."""
        if self._job is not None:
            os.close(self._job)
            self._job = None
            os.kill(self._pid, signal.SIGKILL)
        if self._done is not None:
            os.close(self._done)
            self._done = None
        if self._pid is not None:
            os.waitpid(self._pid, 0)
            self._pid = None


def _warm_up(job: int | None = None) -> None:
    """Import what drawing needs and draw a small figure (fonts, mathtext and the PNG writer loaded); the figure
    is left out when the job ``job`` (a pipe) is already waiting: the study's own first figure loads them then."""
    import io
    import select

    plt = plotting()
    if job is not None and select.select([job], [], [], 0)[0]:
        return
    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([1.0, 10.0], [1.0, 100.0], label="a")
    ax.set(yscale="log", title="t", xlabel="x", ylabel="y")
    ax.legend(fontsize=8)
    png_tight(fig, io.BytesIO())


# ------------------------------------------------------------------------------------------- shared figures
def filter_colours(names) -> dict[str, str]:
    """The colour of each filter, in the order of ``names`` (a study's ``results["filters"]`` or a scenario block's):
    every figure of a study takes its filters' colours from here, so a filter has one colour throughout."""
    return {str(n): PALETTE[i % len(PALETTE)] for i, n in enumerate(names)}


#: Past this many nodes a figure's one line per node gets no legend entry each (a legend of 118 entries squeezed the
#: axes to nothing): the figure says how many lines it draws instead (:func:`node_legend`).
NODE_LEGEND_MAX = 20


def node_label(i: int, nodes: int, first: int = 1) -> str | None:
    """The legend label of the line of node ``i`` (0-based; named from ``first``) among ``nodes`` such lines, None past
    :data:`NODE_LEGEND_MAX`."""
    return f"node {i + first}" if nodes <= NODE_LEGEND_MAX else None


def node_legend(ax, nodes: int, y: float | None = None, **kw) -> None:
    """The legend of a figure's one line per node beside the axes (:func:`legend_beside`; at height ``y`` in axes
    units, centred there, when given), past :data:`NODE_LEGEND_MAX` nodes (their lines unlabelled,
    :func:`node_label`) a note of how many lines there are, and the legend of the other labelled lines."""
    if nodes > NODE_LEGEND_MAX:
        ax.text(0.99, 0.02, f"{nodes} nodes, one line each", fontsize=7, ha="right", va="bottom",
                transform=ax.transAxes)
    if y is None:
        legend_beside(ax, **kw)
    elif ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, ncol=1 if nodes <= 10 else 2, loc="center left", bbox_to_anchor=(1.01, y), **kw)


def legend_beside(ax, **kw) -> None:
    """The legend of ``ax`` to its right, off the data (the figure's constrained layout makes room for it)."""
    if not ax.get_legend_handles_labels()[0]:
        return  # nothing drawn with a label (e.g. a sweep of one value)
    kw.setdefault("fontsize", 7)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, **kw)


def trajectory_figure(path: Path, truth: np.ndarray, estimates: Mapping[str, np.ndarray], sensors: np.ndarray,
                      position: Sequence[int], title: str, colours: Mapping[str, str]) -> None:
    """One run in the plane: the truth, each filter's estimate (in its colour), the sensors."""
    i, j = position
    fig, ax = plotting().subplots(figsize=(7.5, 5))
    ax.plot(sensors[:, 0], sensors[:, 1], "ks", ms=5, label="sensors")
    ax.plot(truth[:, i], truth[:, j], "k-", lw=2, label="truth")
    for name, est in estimates.items():
        ax.plot(est[:, i], est[:, j], lw=1, color=colours.get(name), label=name)
    ax.set(xlabel="x position", ylabel="y position", title=title)
    legend_beside(ax)
    save_figure(fig, path)


def curves_figure(path: Path, curves: Mapping[str, Sequence[float]], ylabel: str, title: str,
                  log: bool = False, colours: Mapping[str, str] | None = None) -> None:
    """Per-step curves (k = 1..K), one line per label (a filter's in its colour of ``colours``)."""
    fig, ax = plotting().subplots(figsize=(8, 4))
    colours = colours or {}
    for label, c in curves.items():
        ax.plot(np.arange(1, len(c) + 1), c, lw=1.2, color=colours.get(label), label=label)
    ax.set(xlabel="time step k", ylabel=ylabel, title=title, yscale="log" if log else "linear")
    legend_beside(ax)
    save_figure(fig, path)


def tradeoff_figure(path: Path, blocks: Sequence) -> None:
    """The summary figure of a study's report: each filter's accuracy (the report's ranking metric, with its 95 %
    interval) against its time per step, its messages in the legend; one panel per scenario (``blocks``: the
    summary's blocks, :func:`studies.reports.study.summary_blocks`).  Nothing is drawn when no filter has both
    numbers."""
    panels = [b for b in blocks if b.drawable]
    if not panels:
        return
    fig, axes = plotting().subplots(1, len(panels), figsize=(5.2 * len(panels) + 3.2, 4.6), squeeze=False)
    counted = any(b.counts_messages for b in panels)
    refs = any(b.references for b in panels)
    for ax, b in zip(axes[0], panels):
        colours = filter_colours(b.filters)
        values = [v for v, _ in b.values.values() if v is not None]
        log = all(v > 0 for v in values)
        for name, (v, ci) in b.values.items():
            t = b.filters[name].get("time_per_step_s")
            if v is None or not isinstance(t, (int, float)) or not t > 0:
                continue
            lo, hi = ci if ci is not None else (v, v)
            ref = name in b.references
            kind = b.kind(name)
            notes = ([b.messages_text(name)] if counted else []) + ([{"global": "oracle"}.get(kind, kind)] if ref else [])
            ax.errorbar(1e3 * t, v, yerr=[[max(v - lo, 0.0)], [max(hi - v, 0.0)]], fmt="o", capsize=3, ms=6,
                        color=colours[name], mfc="white" if ref else colours[name],
                        label=name + (f" ({', '.join(notes)})" if notes else ""))
        ylabel = f"{b.label} with its 95 % interval" + (" (log scale)" if log else "")
        ax.set(xscale="log", yscale="log" if log else "linear", xlabel="time per step (ms, measured, log scale)",
               ylabel="\n".join(textwrap.wrap(ylabel, 48)),
               title=f"{b.title}: accuracy against measured time" if b.title else "accuracy against measured time")
        _plain_log_ticks(ax.xaxis)
        if log:
            _plain_log_ticks(ax.yaxis)
        ax.grid(True, which="both", alpha=0.3)
    notes = (["messages"] if counted else []) + (["hollow: a reference, never the pick"] if refs else [])
    legend_beside(axes[0, -1], title="filter" + (f" ({'; '.join(notes)})" if notes else ""), title_fontsize=7)
    save_figure(fig, path)


def candidates_figure(path: Path, candidates: Sequence[Mapping], references: Mapping, measured: Mapping,
                      pick: int | None, title: str) -> bool:
    """An automatic design's figure (:mod:`studies.auto`): each designed candidate's predicted error (node-average
    tr Φ at the horizon) against its bytes per step (filled: certified; hollow: not), the frontier of the certified
    ones (the least error for at most that many bytes), the pick ringed; the centralized and the local EKFs'
    steady-state tr P at their cost, and, after a validation, the measured mean squared errors (``measured``: name ->
    (bytes per step, mean ‖e‖²), squares) of the pick, KCF, HCMCI and the EKFs.  Nothing is drawn (False) when no
    candidate has a predicted error."""
    pts = [(i, c) for i, c in enumerate(candidates) if isinstance(c.get("predicted_trace"), (int, float))
           and c["predicted_trace"] > 0 and isinstance(c.get("bytes_per_step"), (int, float))]
    if not pts:
        return False
    fig, ax = plotting().subplots(1, 1, figsize=(9.6, 5.0))
    rules_ = sorted({str(c.get("rule")) for _, c in pts})
    colours = filter_colours(rules_)
    for r in rules_:
        mine = [(i, c) for i, c in pts if str(c.get("rule")) == r]
        for certified in (True, False):
            sel = [c for _, c in mine if bool(c.get("certified")) is certified]
            if sel:
                ax.scatter([max(c["bytes_per_step"], 1) for c in sel], [c["predicted_trace"] for c in sel], s=36,
                           color=colours[r], facecolors=colours[r] if certified else "white", zorder=3,
                           label=f"{r}{'' if certified else ' (not certified)'}")
    cert = sorted((max(c["bytes_per_step"], 1), c["predicted_trace"]) for _, c in pts if c.get("certified"))
    front, best = [], math.inf
    for b, v in cert:
        if v < best:
            best = v
            front.append((b, v))
    if front:
        ax.step([b for b, _ in front], [v for _, v in front], where="post", color="0.3", lw=1, zorder=2,
                label="frontier of the certified candidates")
    if pick is not None and 0 <= pick < len(candidates):
        c = candidates[pick]
        if isinstance(c.get("predicted_trace"), (int, float)):
            ax.scatter([max(c["bytes_per_step"], 1)], [c["predicted_trace"]], s=180, facecolors="none",
                       edgecolors="k", linewidths=1.5, zorder=4, label=f"the pick: {c.get('label')}")
    for name, key, marker in (("centralized EKF", "centralized", "D"), ("local EKFs", "local_mean", "v")):
        v, cost = references.get(key), (references.get("costs") or {}).get(name) or {}
        if isinstance(v, (int, float)) and math.isfinite(v) and v > 0:
            ax.scatter([max(cost.get("bytes_per_step") or 0, 1)], [v], marker=marker, s=50, color="0.5", zorder=3,
                       label=f"{name}: steady-state tr P (predicted)")
    for name, (b, v) in measured.items():
        if isinstance(v, (int, float)) and v > 0 and math.isfinite(v):
            ax.scatter([max(b or 0, 1)], [v], marker="s", s=40, facecolors="none", edgecolors="C3", zorder=3)
            ax.annotate(name, (max(b or 0, 1), v), fontsize=7, xytext=(4, 3), textcoords="offset points")
    if measured:
        ax.scatter([], [], marker="s", facecolors="none", edgecolors="C3", label="measured on the fresh runs: mean "
                                                                                "squared error")
    ax.set(xscale="log", yscale="log", xlabel="bytes per step over the network (log scale; 0 drawn at 1)",
           ylabel="node-average tr Φ at the horizon (log scale)", title=title)
    ax.grid(True, which="both", alpha=0.3)
    legend_beside(ax, title="candidates and references", title_fontsize=7)
    save_figure(fig, path)
    return True


def _plain_log_ticks(axis) -> None:
    """Tick labels of a log axis as plain numbers (0.2, 1, 50): one per decade over a long range, at 1, 2 and 5 per
    decade over two decades or less, at every digit within one, so that none overlap and every range has some."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    lo, hi = axis.get_view_interval()
    span = hi / lo if lo > 0 else math.inf
    subs = tuple(range(1, 10)) if span < 10 else (1.0, 2.0, 5.0) if span < 100 else (1.0,)
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    axis.set_major_locator(LogLocator(base=10, subs=subs))
    axis.set_major_formatter(plain)
    axis.set_minor_formatter(NullFormatter())


def _short_rule(label) -> str:
    """A pick's label shortened for a map's cell: ``"flood (rounds=3)"`` -> ``"flood 3"``."""
    import re

    return re.sub(r"[(),]|\w+=", "", str(label or "")).replace("  ", " ").strip()


def map_figure(rows: list[dict], parsed, scenario: str, mode: str):
    """The map's figure: for two grid parameters, the category of every point
    (:data:`studies.feasibility_terms.MAP_CATEGORIES`, each colour in the legend with its count; the QuadMesh's data
    are the indices of the categories, gid ``"categories"``) beside the steady-state trace bound where a fixed point
    exists (log scale); for one, the trace bound against the parameter with a marker per point in its category's
    colour (one labelled line per category, gid ``"category:<name>"``; a point without a bound sits on the lowest
    bound's level).  Points that failed (not mapped) are framed in grey.  ``mode`` ``'auto'``: each point is labelled
    with its pick (gid ``"pick"``)."""
    from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm
    from matplotlib.patches import Patch


    plt = plotting()
    cats = [map_category(r) for r in rows]
    code = np.array([MAP_CATEGORIES.index(c) if c is not None else np.nan for c in cats])
    tb = np.array([r["trace_bound"] if r["feasible"] else np.nan for r in rows], dtype=float)
    failed = np.array([str(r["binding"]).startswith(FAILED) for r in rows])
    counts = {c: cats.count(c) for c in MAP_CATEGORIES}
    label = {c: f"{MAP_WORDS[c]}: {counts[c]}" for c in MAP_CATEGORIES}
    title = (f"{scenario}: the best certified design at each point (auto), at the operating point" if mode == "auto"
             else f"{scenario}: the {mode} consensus design at the operating point")
    if len(parsed) == 1:
        (name, vals), = parsed
        fig, ax = plt.subplots(figsize=(8.5, 4.8))
        level = np.nanmin(tb) if np.any(np.isfinite(tb)) else 1.0
        ax.semilogy(vals, tb, "-", color="0.6", lw=1)
        y = np.where(np.isfinite(tb), tb, level)
        for i, c in enumerate(MAP_CATEGORIES):
            at = code == i
            (line,) = ax.semilogy(vals[at], y[at], "o" if c != "infeasible" else "X", ls="none", ms=7,
                                  color=MAP_COLOURS[c], label=label[c])
            line.set_gid(f"category:{c}")
        if failed.any():
            ax.plot(vals[failed], y[failed], "s", color="grey", mfc="none", ms=11, label="failed (not mapped)")
        if mode == "auto":  # the pick at each point
            for x, yy, r in zip(vals, y, rows):
                ax.annotate(_short_rule(r.get("rule")), (x, yy), textcoords="offset points", xytext=(0, 8),
                            fontsize=6, rotation=60, ha="left", va="bottom", gid="pick")
            ax.margins(y=0.15)
        ax.set(xlabel=name, title=title, ylabel="steady-state tr Φ (mean over nodes)"
               + ("\n(points without a bound: on the lowest level)" if np.isnan(tb).any() else ""))
        ax.legend(fontsize=8, loc="best")
    else:
        (n1, v1), (n2, v2) = parsed
        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5))
        shape = (len(v1), len(v2))
        cmap = ListedColormap([MAP_COLOURS[c] for c in MAP_CATEGORIES])
        norm = BoundaryNorm(np.arange(len(MAP_CATEGORIES) + 1) - 0.5, len(MAP_CATEGORIES))
        mesh = ax.pcolormesh(v2, v1, np.ma.masked_invalid(code.reshape(shape)), cmap=cmap, norm=norm,
                             shading="nearest", edgecolors="white", linewidth=0.5)
        mesh.set_gid("categories")
        handles = [Patch(facecolor=MAP_COLOURS[c], label=label[c]) for c in MAP_CATEGORIES]
        fi, fj = np.nonzero(failed.reshape(shape))
        if fi.size:
            (fail,) = ax.plot(v2[fj], v1[fi], "s", color="grey", mfc="none", ms=9, label="failed (not mapped)")
            handles.append(fail)
        ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
        if mode == "auto":  # the pick at each point
            for k, r in enumerate(rows):
                i, j = divmod(k, len(v2))
                ax.text(v2[j], v1[i], _short_rule(r.get("rule")), ha="center", va="center", fontsize=6, gid="pick")
        ax.set(xlabel=n2, ylabel=n1, title="the verdict at each grid point"
               + (" (and the design picked there)" if mode == "auto" else ""))
        grid = tb.reshape(shape)
        finite = grid[np.isfinite(grid)]
        norm2 = LogNorm(finite.min(), finite.max()) if finite.size and finite.min() > 0 else None
        mesh2 = ax2.pcolormesh(v2, v1, np.ma.masked_invalid(grid), norm=norm2, shading="nearest", cmap="viridis")
        fig.colorbar(mesh2, ax=ax2, label="steady-state tr Φ (mean over nodes)")
        ax2.set(xlabel=n2, ylabel=n1, title="the bound where a fixed point exists (blank: none)")
        fig.suptitle(title, fontsize=10)
    return fig
