"""The figures that the reports of a retrieval share (:mod:`cloudct.retrieval.report` of
the extinction, :mod:`cloudct.retrieval.microphysics_report` of LWC and r_eff): curves of
the log, horizontal slices of a field beside its truth, and images beside the measured
ones; PNG files by matplotlib's Agg back end, written whole or not at all
(:func:`cloudct.output_files.save_figure`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cloudct.output_files import save_figure


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg back end (files only, no window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class Curve(NamedTuple):
    """One line of a :class:`Panel`: its legend label (None: none) and values, and its
    matplotlib line style."""

    label: str | None
    values: np.ndarray
    style: str = "-"


class Panel(NamedTuple):
    """One set of axes of :func:`curves_figure`: its curves, y label and title, a
    logarithmic y axis where ``log``, a line at 0 where ``zero``."""

    curves: Sequence[Curve]
    ylabel: str | None = None
    title: str | None = None
    log: bool = False
    zero: bool = False


def curves_figure(x: np.ndarray, panels: Sequence[Panel], xlabel: str, path: Path) -> None:
    """Side by side, each panel's curves against ``x`` (e.g. the wall time or the
    iteration: integers get integer ticks), written to ``path``."""
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
    whole = np.issubdtype(np.asarray(x).dtype, np.integer)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels) + 0.5, 3.5),
                             squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for curve in panel.curves:
            ax.plot(x, curve.values, curve.style, lw=1, label=curve.label)
        if panel.log:
            ax.set_yscale("log")
        if panel.zero:
            ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(xlabel)
        if whole:
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if panel.ylabel:
            ax.set_ylabel(panel.ylabel)
        if panel.title:
            ax.set_title(panel.title, fontsize=9)
        if any(curve.label for curve in panel.curves):
            ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def slices_figure(rows: Sequence[tuple[str, np.ndarray]], z: np.ndarray, label: str,
                  path: Path, *, vmin: float | None = 0.0) -> None:
    """Horizontal slices of fields over (x, y, z), one row of panels per ``(name, field)``
    of ``rows`` (e.g. the truth's and the retrieved), at four heights from the base to the
    top of the first row's cloud (where its field is positive), on one colour scale
    labelled ``label`` (with the units): from ``vmin`` (None: the fields' least value; NaN
    cells, e.g. clear ones, are left blank) to the fields' greatest value."""
    plt = pyplot()
    first = rows[0][1]
    cloudy = np.nonzero((first > 0).any(axis=(0, 1)))[0]
    low, high = (cloudy[0], cloudy[-1]) if cloudy.size else (0, first.shape[2] - 1)
    ks = np.unique(np.linspace(low, high, 4).round().astype(int))
    fields = [data for _, data in rows]
    top = max(np.nanmax(data, initial=0.0) for data in fields)
    bottom = vmin if vmin is not None else min(np.nanmin(data, initial=top) for data in fields)
    fig, axes = plt.subplots(len(rows), len(ks), figsize=(2.6 * len(ks) + 1.0, 2.6 * len(rows)),
                             squeeze=False, layout="constrained")
    for col, k in enumerate(ks):
        for row, (name, data) in enumerate(rows):
            ax = axes[row, col]
            im = ax.imshow(data[:, :, k].T, origin="lower", vmin=bottom, vmax=top,
                           cmap="viridis")
            ax.set_title(f"{name}, z = {z[k]:.2f} km", fontsize=8)
            ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label=label)
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def images_figure(rows: Sequence[tuple[str, np.ndarray]], path: Path,
                  title: str | None = None) -> None:
    """Images over (view, row, col), one row of panels per ``(name, images)`` of ``rows``
    (the measured first), on the measured images' grey scale (brighter noise saturates;
    NaN pixels, masked, are left blank)."""
    plt = pyplot()
    nv = rows[0][1].shape[0]
    vmax = np.nanmax(rows[0][1])
    fig, axes = plt.subplots(len(rows), nv, figsize=(1.9 * nv, 2.0 * len(rows)), squeeze=False)
    for v in range(nv):
        for row, (name, data) in enumerate(rows):
            axes[row, v].imshow(data[v], cmap="gray", vmin=0, vmax=vmax)
            axes[row, v].set_title(f"{name} {v}", fontsize=7)
            axes[row, v].axis("off")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
