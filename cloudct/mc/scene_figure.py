"""A figure of a scene: the medium's box, the cameras, their fields of view and the sun,
seen from above (x, y) and from the side (x, z), so that a user can check a geometry
before rendering it (``cloudct scene --figure``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cloudct.mc.scene import Scene, corner_rays
from cloudct.output_files import save_figure


def save_scene_figure(scene: Scene, box_min: np.ndarray, box_max: np.ndarray,
                      path: str | Path) -> Path:
    """Write the scene figure to ``path`` (PNG); returns the path.

    Each camera is a dot with its number, a line to the point it looks at and its four
    corner rays (an orthographic camera's from its image corners) drawn to that distance;
    the box is the medium's; the arrow is the direction of the sun's rays.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo = np.asarray(box_min, dtype=float)
    hi = np.asarray(box_max, dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, (i, j), title in zip(axes, ((0, 1), (0, 2)), ("from above", "from the side"),
                                 strict=True):
        ax.add_patch(plt.Rectangle((lo[i], lo[j]), hi[i] - lo[i], hi[j] - lo[j], fill=False,
                                   lw=1.5, color="k", label="medium"))
        for k, cam in enumerate(scene.cameras):
            p = np.asarray(cam.position, dtype=float)
            reach = float(np.linalg.norm(np.subtract(cam.lookat, p)))
            for o, ray in zip(*corner_rays(cam), strict=True):
                q = o + reach * ray
                ax.plot([o[i], q[i]], [o[j], q[j]], color="tab:blue", lw=0.5, alpha=0.5)
            ax.plot([p[i], cam.lookat[i]], [p[j], cam.lookat[j]], color="tab:blue", lw=0.8)
            ax.plot(p[i], p[j], "o", color="tab:blue", ms=4)
            ax.annotate(str(k), (p[i], p[j]), textcoords="offset points", xytext=(3, 3),
                        fontsize=7)
        sun = scene.sun.travel_direction()
        centre = (lo + hi) / 2
        size = 0.5 * float(np.max(hi - lo))
        start = centre - size * sun
        ax.annotate("", xy=(centre[i], centre[j]), xytext=(start[i], start[j]),
                    arrowprops={"arrowstyle": "->", "color": "tab:orange", "lw": 2})
        ax.set_xlabel("xyz"[i] + " [km]")
        ax.set_ylabel("xyz"[j] + " [km]")
        ax.set_aspect("equal")
        ax.set_title(title)
        ax.autoscale_view()
    fig.suptitle(f"{len(scene.cameras)} cameras, sun at zenith {scene.sun.zenith:g} deg "
                 f"(orange: its rays), {scene.boundary} boundaries")
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
