"""PNG plots of an accuracy evaluation (paper Figs. 8–11), drawn with matplotlib's Agg canvas.

matplotlib is imported inside the functions (it is slow to import and the engine never needs it),
and figures are built with :class:`matplotlib.figure.Figure` and an Agg canvas, never through
``pyplot``: no global state, no GUI backend, safe from worker threads and headless machines.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..engine.evaluation.results import Evaluation
from ..io.atomic import atomic_path
from .tables import phase_number

#: Accuracy index the paper uses as the acceptance line (a 15 % error margin).
PAPER_ACCEPTANCE = 0.85
#: One colour per field, in the evaluation's order (the first, usually the uncorrected field,
#: orange; the next, the corrected one, blue): the Evaluate panel's plots use the same.
FIELD_COLORS = ("#f28e2b", "#4e9fde", "#59a14f", "#e15759", "#b07aa1", "#edc948")


def field_color(index: int) -> str:
    """The colour of the ``index``-th field of an evaluation (:data:`FIELD_COLORS`)."""
    return FIELD_COLORS[index % len(FIELD_COLORS)]


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _save(figure, path: str | os.PathLike) -> Path:
    path = Path(path)
    with atomic_path(path) as temp:
        figure.savefig(temp, format="png")
    return path


def _bar_layout(evaluation: Evaluation):
    edges = evaluation.edges
    widths = np.diff(edges)
    n = max(1, len(evaluation.fields))
    return edges, widths, n


def plot_residual_vs_strain(evaluation: Evaluation, path: str | os.PathLike) -> Path:
    """Mean gray residual per equivalent-strain bin, one bar per field (paper Fig. 10).

    Dashed lines mark the background residual ``r0`` used for each field.
    """
    figure = _figure(6.4, 4.0)
    axes = figure.add_subplot()
    edges, widths, n = _bar_layout(evaluation)
    for k, item in enumerate(evaluation.fields):
        offset = edges[:-1] + widths * (k + 0.5) / n
        color = field_color(k)
        axes.bar(
            offset, item.bins.mean_residual, width=widths / n * 0.9, label=item.name, color=color
        )
        axes.axhline(item.background_used, color=color, linestyle="--", linewidth=1)
    axes.set_xlabel("equivalent strain (eq. 3)")
    axes.set_ylabel("mean gray residual (gray levels)")
    axes.set_title("Gray residual against equivalent strain (dashed: background r0)")
    axes.set_xlim(edges[0], edges[-1])
    axes.legend()
    return _save(figure, path)


def plot_accuracy_vs_strain(evaluation: Evaluation, path: str | os.PathLike) -> Path:
    """Accuracy index (eq. 2) per equivalent-strain bin, one line per field (paper Fig. 11)."""
    figure = _figure(6.4, 4.0)
    axes = figure.add_subplot()
    centers = 0.5 * (evaluation.edges[:-1] + evaluation.edges[1:])
    for k, item in enumerate(evaluation.fields):
        axes.plot(centers, item.bin_accuracy, marker="o", label=item.name, color=field_color(k))
    axes.axhline(PAPER_ACCEPTANCE, color="0.4", linestyle=":", linewidth=1, label="0.85 (paper)")
    axes.set_xlabel("equivalent strain (eq. 3)")
    axes.set_ylabel("accuracy index p (eq. 2)")
    first, second = (phase_number(p) for p in evaluation.phase_pair)
    axes.set_title(f"Accuracy index, phases {first} and {second}, |g1 - g2| = "
                   f"{evaluation.contrast:.1f}")  # fmt: skip
    axes.set_xlim(evaluation.edges[0], evaluation.edges[-1])
    axes.legend()
    return _save(figure, path)


def _middle_slices(volume) -> list[tuple[str, np.ndarray]]:
    """The three middle planes of an array or a lazy volume (only they are read)."""
    nz, ny, nx = volume.shape
    return [
        (f"z = {nz // 2}", np.asarray(volume[nz // 2 : nz // 2 + 1, :, :])[0]),
        (f"y = {ny // 2}", np.asarray(volume[:, ny // 2 : ny // 2 + 1, :])[:, 0, :]),
        (f"x = {nx // 2}", np.asarray(volume[:, :, nx // 2 : nx // 2 + 1])[:, :, 0]),
    ]


def _finite_sample(volume, most: int = 2_000_000) -> np.ndarray:
    """Every ``k``-th finite value of an array or a lazy volume in C order (at most ~``most``).

    Read slab by slab, twice (count, then take), so a residual on disk is never loaded whole.
    """
    from ..engine.slabs import iter_slabs

    slabs = list(iter_slabs(volume.shape))
    counts = [int(np.count_nonzero(np.isfinite(np.asarray(volume[zs])))) for zs in slabs]
    stride = max(1, sum(counts) // most)
    parts, offset = [], 0
    for zs, count in zip(slabs, counts):
        values = np.asarray(volume[zs])
        values = values[np.isfinite(values)]
        parts.append(values[(-offset) % stride :: stride])
        offset += count
    return np.concatenate(parts) if parts else np.zeros(0, np.float32)


def plot_residual_slices(evaluation: Evaluation, path: str | os.PathLike) -> Path | None:
    """Three orthogonal middle slices of each field's residual volume (paper Figs. 8–9).

    One row per field, one shared colour scale (0 to the 99th percentile of all residuals).
    Returns None (and writes nothing) when the evaluation kept no residual volumes.
    """
    items = [item for item in evaluation.fields if item.residual is not None]
    if not items:
        return None
    finite = np.concatenate(
        [s[np.isfinite(s)].ravel() for item in items for _, s in _middle_slices(item.residual)]
    )
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    figure = _figure(3.0 * 3 + 0.8, 2.8 * len(items))
    grid = figure.subplots(len(items), 3, squeeze=False)
    image = None
    for row, item in enumerate(items):
        for col, (title, plane) in enumerate(_middle_slices(item.residual)):
            axes = grid[row, col]
            image = axes.imshow(plane, cmap="magma", vmin=0.0, vmax=max(top, 1e-6))
            axes.set_title(f"{item.name}: {title}", fontsize=9)
            axes.set_xticks([])
            axes.set_yticks([])
    figure.colorbar(image, ax=grid, label="gray residual |F(X+u) - G(X)|", shrink=0.8)
    return _save(figure, path)


def plot_residual_histogram(evaluation: Evaluation, path: str | os.PathLike) -> Path | None:
    """Distribution of the residual of each field, with its background ``r0`` (dashed)."""
    indexed = [(k, item) for k, item in enumerate(evaluation.fields) if item.residual is not None]
    if not indexed:
        return None
    samples = [_finite_sample(item.residual) for _, item in indexed]
    top = float(np.percentile(np.concatenate(samples), 99.5)) if samples else 1.0
    bins = np.linspace(0.0, max(top, 1e-6), 80)
    figure = _figure(6.4, 4.0)
    axes = figure.add_subplot()
    for (k, item), values in zip(indexed, samples):
        color = field_color(k)
        axes.hist(values, bins=bins, histtype="step", density=True, label=item.name, color=color)
        axes.axvline(item.background_used, color=color, linestyle="--")
    axes.set_xlabel("gray residual (gray levels)")
    axes.set_ylabel("density")
    axes.set_title("Residual distribution (dashed: background r0)")
    axes.legend()
    return _save(figure, path)
