"""Figure of the nine rendered views of the bundled single cloud (docs/forward_model.md).

    python docs/figures/make_forward_figure.py
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cloudct.mc.render import render, single_cloud_medium  # noqa: E402
from cloudct.mc.scene import single_cloud_scene  # noqa: E402
from cloudct.medium import cell_edges  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    images = render(medium, scene, photons=4_000_000, seed=0, progress=False)
    radiance = images.radiance.values
    rel = images.radiance_std_error.values / np.where(radiance > 0, radiance, np.inf)
    vmax = radiance.max()
    fig, axes = plt.subplots(3, 3, figsize=(8.4, 8.4))
    order = [8, 1, 2, 7, 0, 3, 6, 5, 4]  # ring azimuths laid out around the zenith view
    for ax, view in zip(axes.flat, order, strict=True):
        ax.imshow(radiance[view], cmap="gray", vmin=0, vmax=vmax)
        bright = radiance[view] > 0.1 * radiance[view].max()
        ax.set_title(
            f"view {view}: mean {radiance[view].mean():.4f}\n"
            f"median rel. err. (bright) {np.median(rel[view][bright]):.1%}", fontsize=8,
        )
        ax.axis("off")
    fig.suptitle(
        f"Single cloud (rico32x37x26), sun at zenith, {images.attrs['photons']:,} photons, "
        f"{images.attrs['wall_time']:.0f} s", fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(HERE / "single_cloud_views.png", dpi=110)
    print({"wall_s": images.attrs["wall_time"], "view_means": radiance.mean(axis=(1, 2))})


if __name__ == "__main__":
    main()
