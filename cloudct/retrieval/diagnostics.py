"""Gradient diagnostics: per-voxel means and spreads of each gradient estimator over
independent seeds, and slice figures (in the manner of the DRT paper's Figs. 8-9).

For a scene and pixel weights r_d, each estimator's estimate of g_v = sum_d r_d dI_d/dbeta_v
is repeated with independent seeds; the mean over seeds, the standard deviation of a single
estimate, and the wall time per estimate are returned as a Dataset over
(estimator, x, y, z), so that estimators can be compared at equal time.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.mc.estimate import check_residual
from cloudct.mc.gradient import gradient_estimate, gradient_estimator
from cloudct.mc.scene import Scene
from cloudct.output_files import save_figure


def _estimate(
    estimator: str, medium: xr.Dataset, scene: Scene, residual: np.ndarray, samples: int, seed: int
) -> np.ndarray:
    """One estimate by ``estimator`` with ``samples`` forward photons (score) or samples of
    every pixel with a non-zero residual (camera-side estimators)."""
    residual = check_residual(residual, scene)
    per_pixel = gradient_estimator(estimator).camera_side
    photons = samples * max(int(np.count_nonzero(residual)), 1) if per_pixel else samples
    return gradient_estimate(medium, scene, residual, estimator=estimator, photons=photons,
                             seed=seed)[0]


def gradient_statistics(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    samples: dict[str, int],
    *,
    seeds: int = 8,
) -> xr.Dataset:
    """Per-voxel mean and single-estimate standard deviation of each estimator.

    ``samples`` maps an estimator name ("score": forward photons, "drt" and "sm": backward
    samples per pixel) to its sample count per estimate; ``seeds`` independent estimates are made.
    """
    if seeds < 2:
        raise ValueError("at least two seeds are needed for a spread")
    names = list(samples)
    means, stds, times = [], [], []
    for name in names:
        runs = []
        start = time.perf_counter()
        for seed in range(seeds):
            runs.append(_estimate(name, medium, scene, residual, samples[name], 1000 + seed))
        times.append((time.perf_counter() - start) / seeds)
        runs = np.array(runs)
        means.append(runs.mean(axis=0))
        stds.append(runs.std(axis=0, ddof=1))
    dims = ("estimator", "x", "y", "z")
    coords = {"estimator": names, "x": medium["x"], "y": medium["y"], "z": medium["z"]}
    ds = xr.Dataset(
        {
            "mean": (dims, np.array(means)),
            "std": (dims, np.array(stds)),
            "seconds_per_estimate": ("estimator", np.array(times)),
            "samples": ("estimator", np.array([samples[n] for n in names])),
        },
        coords=coords,
        attrs={"seeds": seeds, "title": "gradient estimator statistics"},
    )
    ds["mean"].attrs.update(units="km", long_name="mean over seeds of sum_d r_d dI_d/dbeta_v")
    ds["std"].attrs.update(units="km", long_name="standard deviation of one estimate")
    ds["seconds_per_estimate"].attrs.update(units="s")
    return ds


def plot_gradient_slices(
    stats: xr.Dataset, path: str | Path, *, z_index: int | None = None,
    reference: np.ndarray | None = None,
) -> Path:
    """Figure of a horizontal slice: each estimator's mean and standard deviation (and a
    reference gradient, e.g. finite differences, when given). Returns the PNG path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nz = stats.sizes["z"]
    k = nz // 2 if z_index is None else int(z_index)
    names = list(stats["estimator"].values)
    ncol = 2 + (reference is not None)
    fig, axes = plt.subplots(len(names), ncol, figsize=(3.4 * ncol, 3.0 * len(names)),
                             squeeze=False)
    scale = float(np.nanmax(np.abs(stats["mean"].values[..., k]))) or 1.0
    spread = float(np.nanmax(stats["std"].values[..., k])) or 1.0
    for row, name in enumerate(names):
        panels = [
            (stats["mean"].values[row, :, :, k], "RdBu_r", -scale, scale, f"{name}: mean"),
            (stats["std"].values[row, :, :, k], "viridis", 0.0, spread, f"{name}: std"),
        ]
        if reference is not None:
            panels.append((reference[:, :, k], "RdBu_r", -scale, scale, "reference"))
        for ax, (data, cmap, lo, hi, title) in zip(axes[row], panels, strict=True):
            im = ax.imshow(data.T, origin="lower", cmap=cmap, vmin=lo, vmax=hi)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("x index")
            ax.set_ylabel("y index")
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"gradient slice z index {k} ({stats.attrs['seeds']} seeds)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
