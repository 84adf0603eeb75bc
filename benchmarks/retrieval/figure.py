"""Loss and epsilon against wall time for retrieval benchmark results (one curve per run).

Reads the JSON files written by ``benchmarks/retrieval/single_cloud.py`` and draws, over
iteration wall time, the loss (a running mean over ``--smooth`` iterations: single losses
carry the Monte Carlo noise of their images), epsilon and delta (seed paper Eq. 54); dotted
lines mark the start of each coarse-to-fine stage (the loss of a finer stage is over other
pixels, so it jumps there). With ``--compile-apart`` the time axis leaves out the seconds
each iteration spent compiling kernels (the log's ``compile_seconds``: a new process on a
GPU, or on a CPU with an empty kernel cache) and each run's label says how many there were,
so that runs on other devices, cold and warm, compare by their iterations. Usage::

    python -m benchmarks retrieval.figure RESULT.json [RESULT.json ...] --labels A B ...
        --output docs/figures/retrieval_single_cloud.png [--compile-apart]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of each value and the ``window - 1`` before it (fewer at the start)."""
    c = np.concatenate([[0.0], np.cumsum(values)])
    i = np.arange(1, values.size + 1)
    lo = np.maximum(i - window, 0)
    return (c[i] - c[lo]) / (i - lo)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+")
    parser.add_argument("--labels", nargs="+", default=None)
    parser.add_argument("--smooth", type=int, default=10)
    parser.add_argument("--output", required=True)
    parser.add_argument("--compile-apart", action="store_true",
                        help="time without the compile seconds, given in each label")
    args = parser.parse_args()
    labels = args.labels or [Path(r).stem for r in args.results]
    if len(labels) != len(args.results):
        parser.error("give one label per result file")

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for path, label in zip(args.results, labels, strict=True):
        result = json.loads(Path(path).read_text())
        log = result["log"]
        seconds = np.asarray(log["seconds"])
        if args.compile_apart:
            compiled = np.cumsum(log.get("compile_seconds", np.zeros(seconds.size)))
            seconds = seconds - compiled
            label = f"{label} (+{compiled[-1]:.0f} s compiling)"
        minutes = seconds / 60.0
        line = axes[0].plot(
            minutes, running_mean(np.asarray(log["loss"]), args.smooth), label=label
        )[0]
        axes[1].plot(minutes, log["epsilon"], label=label)
        axes[2].plot(minutes, log["delta"], label=label)
        for start in np.nonzero(np.diff(log["stage"]))[0] + 1:
            for ax in axes:
                ax.axvline(minutes[start], color=line.get_color(), ls=":", lw=1)
    axes[0].set(yscale="log", ylabel=f"loss (running mean of {args.smooth})")
    axes[1].set(ylabel="epsilon")
    axes[2].set(ylabel="delta")
    for ax in axes:
        ax.set_xlabel("iteration wall time" + (", compiling apart" if args.compile_apart
                                               else "") + " [min]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=120)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
