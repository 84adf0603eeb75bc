"""Epsilon, the step and the photons per iteration against wall time, for retrieval runs
of the step-schedule comparison (issue 35): one row of panels per scene.

Each run is ``SCENE:LABEL=FILE``, FILE a ``benchmarks/retrieval/single_cloud.py`` JSON
(its ``log``) or a ``cloudct retrieve`` result netCDF (its ``log_*`` variables); a run
whose log has no ``step`` column (runs from before the schedule) is drawn in epsilon
only. Usage::

    python -m benchmarks retrieval.schedule_figure "single cloud:new=a.json" \\
        "single cloud:old=b.json" "cloud field:new=c.nc" --output docs/figures/schedule.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def run_log(path: Path) -> dict[str, np.ndarray]:
    """The per-iteration log of a run file (JSON of the benchmark, or a result netCDF)."""
    if path.suffix == ".json":
        log = json.loads(path.read_text())["log"]
        return {k: np.asarray(v, dtype=float) for k, v in log.items()}
    import xarray as xr

    ds = xr.load_dataset(path)
    return {name.removeprefix("log_"): ds[name].values for name in ds.data_vars
            if name.startswith("log_")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="SCENE:LABEL=FILE")
    parser.add_argument("--output", type=Path, default=Path("docs/figures/schedule.png"))
    args = parser.parse_args()
    scenes: dict[str, list[tuple[str, dict]]] = {}
    for spec in args.runs:
        scene, _, rest = spec.partition(":")
        label, _, file = rest.partition("=")
        scenes.setdefault(scene, []).append((label, run_log(Path(file))))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(scenes), 3, figsize=(13, 3.2 * len(scenes)), squeeze=False)
    for row, (scene, runs) in zip(axes, scenes.items(), strict=True):
        for label, log in runs:
            minutes = log["seconds"] / 60
            line = row[0].plot(minutes, log["epsilon"], label=label)[0]
            if "step" in log and np.isfinite(log["step"]).any():
                row[1].semilogy(minutes, log["step"], color=line.get_color(), label=label,
                                drawstyle="steps-post")
                row[2].semilogy(minutes, log["photons"], color=line.get_color(), label=label,
                                drawstyle="steps-post")
        row[0].set_ylabel(f"{scene}\nepsilon")
        row[1].set_ylabel("step [1/km]")
        row[2].set_ylabel("photons per iteration\n(gradient and images)")
        row[0].legend(fontsize=7)
        for ax in row:
            ax.set_xlabel("wall time [min], 2 CPU cores")
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=110)
    plt.close(fig)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
