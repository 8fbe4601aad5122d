"""Charts of results: curves, bars and training curves, and labels placed where they overlap
least. Built as gns.plots builds its figures (matplotlib's object API, no pyplot), written
atomically; every function writes `path` and returns it as a Path."""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from gns.plots import new_figure, save_figure
from plumbing import atomic_file

# Offsets (points) tried around a point, nearest first, with the text alignment each needs.
_LABEL_OFFSETS = [((5, 3), "left", "bottom"), ((5, -3), "left", "top"), ((-5, 3), "right", "bottom"),
                  ((-5, -3), "right", "top"), ((0, 7), "center", "bottom"), ((0, -7), "center", "top"),
                  ((12, 0), "left", "center"), ((-12, 0), "right", "center"), ((5, 13), "left", "bottom"),
                  ((5, -13), "left", "top"), ((-5, 13), "right", "bottom"), ((-5, -13), "right", "top"),
                  ((0, 20), "center", "bottom"), ((0, -20), "center", "top")]


def plot_curve(xs: Sequence[float], ys_by_label: Mapping[str, Sequence], path, baseline=None,
               xlabel: str = "number of training tosses", ylabel: str = "position error [% of width]",
               log2: bool = True, title: str | None = None, dpi: int = 120) -> Path:
    """Error against a swept quantity (Figure 4/5/7 style), one line per label.

    ys_by_label: {label: (len(xs),) values, or (len(xs), S) over S seeds -> mean with a min-max
    band}; NaN marks a missing point. baseline: a number, or {label: number}, drawn as
    horizontal dashed lines (e.g. an analytic simulator's error). log2: x axis in powers of 2.
    """
    xs = np.asarray(xs, np.float64)
    fig = new_figure((5.5, 4))
    ax = fig.subplots()
    for i, (label, ys) in enumerate(ys_by_label.items()):
        ys = np.asarray(ys, np.float64).reshape(len(xs), -1)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN x gives NaN: a gap, on purpose
            mean, low, high = np.nanmean(ys, axis=1), np.nanmin(ys, axis=1), np.nanmax(ys, axis=1)
        ax.plot(xs, mean, "o-", color=f"C{i}", label=label, ms=4)
        if ys.shape[1] > 1:
            ax.fill_between(xs, low, high, color=f"C{i}", alpha=0.2, lw=0)
    if baseline is not None:
        items = baseline.items() if isinstance(baseline, Mapping) else [("baseline", baseline)]
        for j, (label, value) in enumerate(items):
            ax.axhline(float(value), ls="--", color=f"C{len(ys_by_label) + j}", lw=1.2, label=label)
    if log2:
        ax.set_xscale("log", base=2)
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{x:g}" for x in xs])
        ax.minorticks_off()
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path, dpi)


def plot_bars(labels: Sequence[str], panels: Mapping[str, Sequence[float]], path,
              references: Mapping[str, Mapping[str, float]] | None = None, title: str | None = None,
              dpi: int = 120) -> Path:
    """Bar charts side by side, one panel per metric (Figure 5 style: ablations).

    panels: {panel y-label: one value per label (NaN: no bar)}; references: {panel y-label:
    {name: value}} drawn as dashed horizontal lines (e.g. a baseline or the full model).
    """
    fig = new_figure((3.2 * len(panels) + 0.5, 3.8))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    x = np.arange(len(labels))
    for ax, (ylabel, values) in zip(axes, panels.items()):
        values = np.asarray(values, np.float64)
        ax.bar(x, np.nan_to_num(values, nan=0.0), color=[f"C{i}" for i in range(len(labels))], alpha=0.85)
        for xi, v in zip(x, values):
            ax.text(xi, 0 if np.isnan(v) else v, "n/a" if np.isnan(v) else f"{v:.3g}", ha="center",
                    va="bottom", fontsize=7)
        refs = (references or {}).get(ylabel, {})
        for j, (name, value) in enumerate(refs.items()):
            ax.axhline(float(value), ls="--", lw=1.2, color=f"C{len(labels) + j}", label=name)
        top = np.nanmax(np.concatenate([values, np.asarray(list(refs.values()), np.float64), [0.0]]))
        # Headroom above the tallest bar for its value label and the legend, so neither hides the other.
        ax.set_ylim(0, 1.3 * top if top > 0 else 1.0)
        if refs:
            ax.legend(fontsize=7, loc="upper left")
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path, dpi)


def plot_training_curves(runs: Mapping[str, Sequence[Mapping]], path, log_loss: bool = True, dpi: int = 110) -> Path:
    """Training curves of runs {label: metrics.jsonl entries}: training loss (solid) and
    validation loss (dashed) against the step, the validation rollout error, the learning rate.
    Panels with no data in any run say so rather than vanish, so figures of runs stay alike.
    Written atomically (a temporary file, then renamed): a reader never sees half an image."""
    panels = (("loss", "normalised acceleration loss"), ("valid_rollout_position_error", "valid rollout centre error [scene units]"),
              ("lr", "learning rate"))
    fig = new_figure((13, 3.8))
    axes = fig.subplots(1, len(panels))
    for i, (label, entries) in enumerate(runs.items()):
        color = f"C{i % 10}"
        for ax, (key, title) in zip(axes, panels):
            keys = (key, "valid_loss") if key == "loss" else (key,)
            for k in keys:
                pts = [(e["step"], e[k]) for e in entries if isinstance(e.get(k), (int, float))]
                if pts:
                    xs, ys = zip(*pts)
                    ax.plot(xs, ys, color=color, ls="--" if k == "valid_loss" else "-",
                            marker="o" if len(pts) < 3 else None, ms=3,
                            label=f"{label}, {'valid' if k == 'valid_loss' else 'train'}" if key == "loss" else label)
    for ax, (key, title) in zip(axes, panels):
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        if not ax.lines:
            ax.text(0.5, 0.5, "not logged", ha="center", va="center", transform=ax.transAxes, color="gray")
            continue
        if key == "lr" or (log_loss and key == "loss"):
            ax.set_yscale("log")
    if axes[0].lines:
        axes[0].legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # matplotlib picks the format from the file's ending, so the temporary file keeps it
    with atomic_file(path, mode=0o644, suffix=path.suffix) as tmp:
        fig.savefig(tmp, dpi=dpi)
    return path


def plot_runs(runs: Sequence[str | Path], out: str | Path, log_loss: bool = True) -> tuple[Path, int]:
    """`gns plot-curves`: the training curves of run folders (or their metrics.jsonl files), overlaid,
    written to `out` (.png, .pdf or .svg); checked before anything is drawn, each problem one line.
    Returns (out, the number of runs drawn)."""
    from plumbing import DataError, check_writable
    from gns.run_folder import METRICS, read_metrics

    out = Path(out)
    if out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise DataError(f"--out {out}: give a .png, .pdf or .svg file name")
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; give a file name such as {out / 'curves.png'}")
    curves = {}
    for run in runs:
        path = Path(run)
        path = path / METRICS if path.is_dir() else path
        if not path.is_file():
            raise DataError(f"no {METRICS} in {run}: not a training run folder")
        entries = read_metrics(path)
        if not entries:
            raise DataError(f"{path} holds no metrics yet")
        label = Path(run).name if Path(run).is_dir() else Path(run).parent.name
        curves[label if label not in curves else str(run)] = entries
    check_writable(out.parent, "output folder")
    return plot_training_curves(curves, out, log_loss=log_loss), len(curves)


def _overlap(a, b) -> float:
    w = min(a.x1, b.x1) - max(a.x0, b.x0)
    h = min(a.y1, b.y1) - max(a.y0, b.y0)
    return w * h if w > 0 and h > 0 else 0.0


def label_points(ax, xs: Sequence[float], ys: Sequence[float], labels: Sequence[str], fontsize: float = 7,
                 marker_px: float = 5.0) -> list:
    """Annotate each (x, y) with its label at the offset, among a few around it, whose text box
    overlaps least with the labels already placed, every marker and the axes' edge (greedy, in
    the given order). Call after the axes' limits and scales are final. Returns the texts."""
    fig = ax.figure
    fig.canvas.draw()   # the transforms and the renderer of the final layout
    renderer = fig.canvas.get_renderer()
    from matplotlib.transforms import Bbox
    pts = ax.transData.transform(np.column_stack([xs, ys])) if len(xs) else np.zeros((0, 2))
    markers = [Bbox.from_extents(px - marker_px, py - marker_px, px + marker_px, py + marker_px) for px, py in pts]
    frame = ax.get_window_extent(renderer)
    placed, texts = [], []
    for x, y, label in zip(xs, ys, labels):
        best = None
        for offset, ha, va in _LABEL_OFFSETS:
            text = ax.annotate(label, (x, y), xytext=offset, textcoords="offset points", fontsize=fontsize,
                               ha=ha, va=va)
            box = text.get_window_extent(renderer)
            outside = box.width * box.height - _overlap(box, frame)
            cost = sum(_overlap(box, b) for b in placed) + sum(_overlap(box, m) for m in markers) + 2 * outside
            if best is None or cost < best[0]:
                if best is not None:
                    best[1].remove()
                best = (cost, text, box)
            else:
                text.remove()
            if cost == 0:
                break
        placed.append(best[2])
        texts.append(best[1])
    return texts


def log_x_axis(ax, suffix: str = "") -> None:
    """A log x axis ticked at 1, 2 and 5 of each decade, written as plain numbers (+ suffix): cost
    and speed ratios span one or two decades, where matplotlib's powers of ten say little."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}{suffix}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
