"""The figures' drawing (studies.figures): one draw instead of two, in parallel processes, by a helper process.

References: matplotlib's own ``savefig(bbox_inches="tight")`` for the single-draw crop, and
the serial drawing for every parallel path (the same bytes whoever draws).
"""
from __future__ import annotations

import io
import os
import sys

import numpy as np
import pytest

from studies import figures as F

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parallel paths fork (Linux)")


def _figure(seed: int, log: bool = True, outside: bool = False):
    rng = np.random.default_rng(seed)
    fig, ax = F.plotting().subplots(figsize=(7, 4), layout=None)  # its artists fit its canvas, legend aside
    for i in range(3):
        ax.plot(np.arange(1, 51), rng.random(50) + 0.01, label=f"filter {i}")
    ax.set(xlabel="time step k", ylabel="RMSE", title=f"figure {seed}", yscale="log" if log else "linear")
    if outside:  # a legend beyond the canvas: matplotlib's tight save widens it
        ax.legend(loc="upper left", bbox_to_anchor=(1.05, 1.0))
    else:
        ax.legend(fontsize=8)
    return fig


def _pixels(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGBA")).astype(int)


@pytest.mark.parametrize("log", [True, False])
def test_single_draw_is_matplotlibs_tight_save_to_a_pixel(log):
    ref, ours = io.BytesIO(), io.BytesIO()
    _figure(1, log).savefig(ref, format="png", dpi=F.FIGURE_DPI, bbox_inches="tight")
    fig = _figure(1, log)
    dpi = fig.get_dpi()
    fig.savefig = None  # the single draw, not matplotlib's tight save (its fallback)
    F.png_tight(fig, ours)
    assert fig.get_dpi() == dpi  # left as savefig leaves it
    a, b = _pixels(ref.getvalue()), _pixels(ours.getvalue())
    assert abs(a.shape[0] - b.shape[0]) <= 2 and abs(a.shape[1] - b.shape[1]) <= 2
    h, w = min(a.shape[0], b.shape[0]) - 2, min(a.shape[1], b.shape[1]) - 2
    best = min(np.abs(a[i:i + h, j:j + w] - b[k:k + h, m:m + w]).mean()
               for i in range(3) for j in range(3) for k in range(3) for m in range(3))
    # anti-aliasing at a sub-pixel offset; a misplaced crop (rows flipped, a margin lost) differs by tens
    assert best < 3.0, best
    dark = (b[..., :3].sum(-1) < 300).mean()  # the lines and text are there, not a blank canvas
    assert 0.005 < dark < 0.3


def test_an_artist_beyond_the_canvas_takes_matplotlibs_tight_save():
    ref, ours = io.BytesIO(), io.BytesIO()
    _figure(2, outside=True).savefig(ref, format="png", dpi=F.FIGURE_DPI, bbox_inches="tight")
    F.png_tight(_figure(2, outside=True), ours)
    assert ours.getvalue() == ref.getvalue()


def test_a_legend_beside_the_axes_fits_the_canvas_and_is_drawn_once():
    """The studies' figures (constrained layout) keep a legend beside the axes on their canvas: drawn once, and
    the legend is in the picture (the right part of it is not blank)."""
    fig, ax = F.plotting().subplots(figsize=(7, 4))
    for i in range(3):
        ax.plot(np.arange(10), np.arange(10) * (i + 1), label=f"a long filter name {i} (8 msgs/step)")
    F.legend_beside(ax)
    fig.savefig = None  # a fallback to matplotlib's tight save would fail here
    out = io.BytesIO()
    F.png_tight(fig, out)
    px = _pixels(out.getvalue())
    legend = px[:, int(0.8 * px.shape[1]):, :3]
    assert (legend.sum(-1) < 300).mean() > 0.002  # the legend's text is there


def _paths(d, n):
    return [d / f"fig_{i}.png" for i in range(n)]


@linux
@pytest.mark.parametrize("processes", [2, 3])
def test_parallel_drawing_writes_the_serial_files(tmp_path, processes):
    n = 5
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    F.draw_figures([(_figure(i, log=i % 2 == 0), p) for i, p in enumerate(_paths(tmp_path / "a", n))], 1)
    F.draw_figures([(_figure(i, log=i % 2 == 0), p) for i, p in enumerate(_paths(tmp_path / "b", n))], processes)
    for pa, pb in zip(_paths(tmp_path / "a", n), _paths(tmp_path / "b", n)):
        assert pa.read_bytes() == pb.read_bytes()
    assert sorted(os.listdir(tmp_path / "b")) == sorted(p.name for p in _paths(tmp_path / "b", n))  # no temp files


@linux
def test_figures_a_child_failed_to_draw_are_drawn_by_the_caller(tmp_path, monkeypatch):
    parent = os.getpid()
    real = F.png_tight

    def fails_in_children(fig, fh, dpi=F.FIGURE_DPI):
        if os.getpid() != parent:
            raise RuntimeError("a child's failure")
        real(fig, fh, dpi)

    monkeypatch.setattr(F, "png_tight", fails_in_children)
    paths = _paths(tmp_path, 4)
    F.draw_figures([(_figure(i), p) for i, p in enumerate(paths)], 2)
    assert all(p.stat().st_size > 1000 for p in paths)


def test_a_batch_that_raises_draws_nothing(tmp_path):
    with pytest.raises(ValueError, match="inside"):
        with F.figure_batch():
            F.save_figure(_figure(0), tmp_path / "x.png")
            raise ValueError("inside")
    assert not (tmp_path / "x.png").exists()
    with F.figure_batch(processes=1):
        F.save_figure(_figure(0), tmp_path / "y.png")
        assert not (tmp_path / "y.png").exists()  # drawn when the batch ends
    assert (tmp_path / "y.png").exists()


def _draw_three(out, results, arrays):
    for i in range(results["n"]):
        F.save_figure(_figure(int(arrays["seeds"][i])), out / f"fig_{i}.png")


def _draw_fails(out, results, arrays):
    raise RuntimeError("the helper's figure code failed")


@linux
def test_the_helper_draws_what_the_study_would(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    results, arrays = {"n": 3}, {"seeds": np.array([4, 5, 6])}
    helper = F.FigureHelper.start(_draw_three)
    assert helper.send(tmp_path / "a", results, arrays) and helper.wait()
    with F.figure_batch(processes=1):
        _draw_three(tmp_path / "b", results, arrays)
    for pa, pb in zip(_paths(tmp_path / "a", 3), _paths(tmp_path / "b", 3)):
        assert pa.read_bytes() == pb.read_bytes()


@linux
def test_a_failing_or_unused_helper_is_reaped(tmp_path):
    helper = F.FigureHelper.start(_draw_fails)
    pid = helper._pid
    assert helper.send(tmp_path, {}, {}) and helper.wait() is False  # the caller then draws itself
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)
    helper = F.FigureHelper.start(_draw_three)  # given nothing: killed at once, not left importing
    pid = helper._pid
    helper.close()
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)


def test_the_other_files_are_written_while_the_helper_draws_and_the_report_after_it(tmp_path):
    from studies.outputs import write_outputs

    seen = {}

    def figures(stage):
        def wait():  # called once table.md and results.json are in place, before the report
            seen["at_wait"] = sorted(p.name for p in stage.iterdir())
            F.save_figure(_figure(1), stage / "fig_a.png")
        return wait

    out = write_outputs(tmp_path / "out", {"x": 1.0}, figures, lambda r: "| table |\n")
    assert seen["at_wait"] == ["results.json", "table.md"]
    assert "fig_a.png" in (out / "report.md").read_text()  # the report was written from the figure


def test_the_warm_up_leaves_out_its_figure_when_the_job_is_waiting(monkeypatch):
    drawn = []
    monkeypatch.setattr(F, "png_tight", lambda fig, fh, dpi=None: drawn.append(fig))
    r, w = os.pipe()
    try:
        F._warm_up(r)  # nothing sent yet: it draws its throwaway figure
        assert len(drawn) == 1
        os.write(w, b"x")
        F._warm_up(r)  # the job is there: the study's first figure loads the fonts instead
        assert len(drawn) == 1
    finally:
        os.close(r)
        os.close(w)


@linux
def test_forking_a_drawer_leaves_this_processs_garbage_collection_as_it_was(monkeypatch):
    import gc

    helper = F.FigureHelper.start(_draw_three)
    try:
        assert gc.get_freeze_count() == 0 and gc.isenabled()
    finally:
        helper.close()

    def no_more_processes():
        raise OSError("fork failed")

    from studies.runner import fork_worker

    monkeypatch.setattr(os, "fork", no_more_processes)
    with pytest.raises(OSError):
        fork_worker(os.getpid())
    assert gc.get_freeze_count() == 0  # a failed fork leaves nothing frozen either


@linux
@pytest.mark.parametrize("name, kw", [
    ("rrp-deception", dict(runs=2, particles=60)),
    ("binary-multi-attack", dict(runs=2, particles=60)),
    ("encrypted-switching", dict(runs=2)),
    ("fdi-four-tank", dict(runs=2)),
    ("consensus-robot", dict(runs=3)),
    ("comparison", dict(runs=2, particles=60, assignments=["sweep_values=[0.2]"])),
])
@pytest.mark.slow
def test_every_studys_helper_draws_its_figures_as_this_process_would(tmp_path, monkeypatch, name, kw):
    """The helper runs a study's figure code on the scenarios as they were before the computation: a figure that
    read state the computation leaves on a scenario would differ from the one drawn here afterwards."""
    import studies
    from studies.outputs import study_figures

    answers = []
    real = F.FigureHelper.wait

    def wait(self):
        answers.append(real(self))
        return answers[-1]

    monkeypatch.setattr(F.FigureHelper, "wait", wait)
    r = studies.study(name, out=str(tmp_path / "helper"), seed=3, **kw)
    assert answers == [True]  # the helper drew them (not this process, after a failure)
    r.save(tmp_path / "here")  # no helper: this process draws
    pngs = sorted(p.name for p in (tmp_path / "helper").glob("*.png"))
    assert pngs and pngs == sorted(p.name for p in (tmp_path / "here").glob("*.png"))
    for p in pngs:
        assert (tmp_path / "helper" / p).read_bytes() == (tmp_path / "here" / p).read_bytes(), p
    # one colour per filter: every figure of the study draws each filter in the colour of the shared mapping
    figs = _drawn(lambda: study_figures(r.study, tmp_path / "here", r.results, r.scenarios, r.arrays))
    assert sorted(path.name for _, path in figs) == pngs and "fig_tradeoff.png" in pngs
    blocks = r.results.get("by_scenario") or {"": r.results}
    colours = {n: c for b in blocks.values() for n, c in F.filter_colours(b["filters"]).items()}
    checked = {path.name: _filter_colours_in(fig, colours) for fig, path in figs}
    assert sum(len(v[0]) for v in checked.values()) >= len(colours)  # filters do appear in legends
    assert {name: v[1] for name, v in checked.items() if v[1]} == {}


def _drawn(draw) -> list:
    """The (figure, path) pairs ``draw`` saves, captured before they are drawn."""
    pending: list = []
    token = F._PENDING.set(pending)
    try:
        draw()
    finally:
        F._PENDING.reset(token)
    return pending


def _filter_colours_in(fig, colours: dict) -> tuple[list, list]:
    """(legend entries naming a filter, those whose colour is not the filter's) over every axes of ``fig``; an
    entry names a filter when its label is the name or the name followed by " (" (the longest such name)."""
    from matplotlib.colors import to_hex

    seen, wrong = [], []
    for ax in fig.axes:
        leg = ax.get_legend()
        if leg is None:
            continue
        for handle, text in zip(leg.legend_handles, leg.get_texts()):
            label = text.get_text()
            names = [n for n in colours if label == n or label.startswith(n + " (")]
            if not names:
                continue
            name = max(names, key=len)
            colour = handle.get_color() if hasattr(handle, "get_color") else handle.get_edgecolor()[0]
            seen.append(label)
            if to_hex(colour) != to_hex(colours[name]):
                wrong.append((label, to_hex(colour), colours[name]))
    return seen, wrong


def test_filter_colours_are_one_mapping_in_order():
    names = [f"filter {i}" for i in range(len(F.PALETTE) + 2)]
    c = F.filter_colours(names)
    assert list(c) == names and c == F.filter_colours(names)
    assert len(set(list(c.values())[:len(F.PALETTE)])) == len(F.PALETTE)  # distinct as far as the palette goes
    assert not {"#000000", "#7f7f7f"} & set(F.PALETTE)  # black and grey stay for the truth and the sensors
    assert F.filter_colours(names[:3]) == {n: c[n] for n in names[:3]}  # a filter's colour is its position's


def test_the_colour_check_sees_a_figure_that_ignores_the_mapping():
    colours = F.filter_colours(["a", "b"])
    fig, ax = F.plotting().subplots()
    ax.plot([0, 1], [0, 1], label="a")
    ax.plot([0, 1], [1, 0], color=colours["a"], label="b (node 1)")  # the default cycle's second colour differs
    F.legend_beside(ax)
    seen, wrong = _filter_colours_in(fig, colours)
    assert seen == ["a", "b (node 1)"] and [w[0] for w in wrong] == ["b (node 1)"]


@pytest.mark.parametrize("nodes", [3, F.NODE_LEGEND_MAX, F.NODE_LEGEND_MAX + 1, 118])
def test_one_line_per_node_names_the_nodes_in_a_legend_only_while_it_fits(nodes, tmp_path):
    """node_label and node_legend: up to NODE_LEGEND_MAX nodes each line is named beside the axes (1-based), with
    the figure's other labelled lines; past it the nodes' lines are unnamed, a note says how many there are and the
    other lines keep their legend, and the figure saves without matplotlib's warning that its axes collapsed (a
    118-entry legend beside a 4-inch figure squeezed them to nothing)."""
    import warnings

    fig, ax = F.plotting().subplots(figsize=(8, 4))
    ax.plot(np.arange(5), np.zeros(5), "k-", label="truth")
    for i in range(nodes):
        ax.plot(np.arange(5), np.full(5, i + 1.0), label=F.node_label(i, nodes))
    F.node_legend(ax, nodes)
    names = [t.get_text() for t in ax.get_legend().get_texts()]
    notes = [t.get_text() for t in ax.texts]
    if nodes <= F.NODE_LEGEND_MAX:
        assert names == ["truth"] + [f"node {i + 1}" for i in range(nodes)] and not notes
    else:
        assert names == ["truth"] and notes == [f"{nodes} nodes, one line each"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        F.save_figure(fig, tmp_path / "nodes.png")
    assert F.node_label(4, nodes, first=0) == ("node 4" if nodes <= F.NODE_LEGEND_MAX else None)
