"""Pieces the benchmark scripts share: the run header of a result file, Markdown tables,
the writing of results, and runs of cloudct commands with the error of a retrieval over
time, as numbers and as a figure."""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import xarray as xr


def run_header() -> dict:
    """Machine, numba threads, load average, date and the exact command of this run."""
    return {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "numba_threads": int(os.environ.get("NUMBA_NUM_THREADS", os.cpu_count())),
        "load_average_start": os.getloadavg(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "command": " ".join(sys.argv),
    }


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """The lines of a Markdown table with this header and these (formatted) cells."""
    return [
        "| " + " | ".join(header) + " |",
        "|" + " --- |" * len(header),
        *("| " + " | ".join(row) + " |" for row in rows),
    ]


def write_json_and_markdown(result: dict, output: str, markdown: Callable[[dict], str]) -> None:
    """``output``.json and ``output``.md (the table ``markdown`` makes), also printed."""
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2))
    out.with_suffix(".md").write_text(markdown(result))
    print(markdown(result))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


def run_command(argv: list[str], log: list[dict]) -> None:
    """Run one cloudct command as a user types it (printed), time it into ``log``; stop on
    failure."""
    from cloudct.cli import main as cloudct

    print("$ cloudct " + shlex.join(argv), flush=True)
    start = time.perf_counter()
    status = cloudct(argv)
    log.append({"command": "cloudct " + shlex.join(argv), "seconds": time.perf_counter() - start})
    if status != 0:
        raise SystemExit(f"cloudct {argv[0]} failed with status {status}")


def error_over_time(result: str | Path, minutes=(5, 15, 30, 60)) -> dict:
    """Iterations, epsilon and delta of a retrieval result file at each of ``minutes`` that
    the run lasted (the last iteration done by then), and at its end."""
    ds = xr.load_dataset(result)
    seconds = ds["log_seconds"].values
    marks = {}
    for m in minutes:
        if 60 * m > 1.01 * seconds[-1]:
            break
        done = np.flatnonzero(seconds <= 60 * m)
        if done.size:
            i = done[-1]
            marks[f"{m:g} min"] = {"iteration": int(i + 1),
                                   "epsilon": float(ds["log_epsilon"].values[i]),
                                   "delta": float(ds["log_delta"].values[i])}
    return {"iterations": int(seconds.size), "seconds": float(seconds[-1]),
            "final": {"epsilon": float(ds["log_epsilon"].values[-1]),
                      "delta": float(ds["log_delta"].values[-1])},
            "over_time": marks}


def error_figure(runs: dict[str, Path], path: Path, title: str) -> None:
    """Epsilon and delta against wall time of retrieval results (``cloudct retrieve``'s
    netCDF files), one curve per ``label: file`` of ``runs``, saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for label, result in runs.items():
        ds = xr.load_dataset(result)
        minutes = ds["log_seconds"].values / 60
        axes[0].plot(minutes, ds["log_epsilon"].values, label=label)
        axes[1].plot(minutes, ds["log_delta"].values, label=label)
    axes[0].set_ylabel("epsilon")
    axes[1].set_ylabel("delta (> 0: extinction missing)")
    axes[1].axhline(0.0, color="k", lw=0.6)
    for ax in axes:
        ax.set_xlabel("wall time [min], 2 CPU cores")
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
