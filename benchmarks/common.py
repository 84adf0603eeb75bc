"""Pieces the benchmarks share: where results and work files go, the run header of a
result file (machine, versions, commit, date, command and settings), Markdown tables, the
writing of results, and runs of cloudct commands with the error of a retrieval over time,
as numbers and as a figure."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.retrieval.state import SHELL_PARTS

#: The benchmarks package, its result and work folders, and the repository.
ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"
WORK = ROOT / "work"
REPO = ROOT.parent

#: Distributions whose versions a result records.
VERSIONED = ("numpy", "numba", "numba-cuda", "scipy", "xarray")


def versions() -> dict[str, str]:
    """The versions of Python, cloudct and :data:`VERSIONED` (None where not installed)."""
    from importlib import metadata

    from cloudct import __version__

    found = {"python": platform.python_version(), "cloudct": __version__}
    for name in VERSIONED:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    return found


def commit() -> str | None:
    """The repository's commit (with ``+changes`` when the work tree differs), or None."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "cloudct"], cwd=REPO,
                               text=True, capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+changes" if dirty else "")


def run_header(args: argparse.Namespace | None = None) -> dict:
    """What a result records of its run: machine, numba threads, load average, versions,
    commit (``+changes``: cloudct's sources differ from it), date, the exact command and,
    given the parsed ``args``, every setting it ran with."""
    import numba

    header = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "numba_threads": numba.get_num_threads(),
        "load_average_start": os.getloadavg(),
        "versions": versions(),
        "commit": commit(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "command": shlex.join(["python", "-m", _module_name(), *sys.argv[1:]]),
    }
    if args is not None:
        header["settings"] = {k: (str(v) if isinstance(v, Path) else v)
                              for k, v in vars(args).items()}
    return header


def _module_name() -> str:
    """The benchmark's module as ``python -m`` names it (its file if it was run as one)."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return spec.name if spec is not None else sys.argv[0]


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """The lines of a Markdown table with this header and these (formatted) cells."""
    return [
        "| " + " | ".join(header) + " |",
        "|" + " --- |" * len(header),
        *("| " + " | ".join(row) + " |" for row in rows),
    ]


def header_markdown(result: dict) -> list[str]:
    """The lines of a result's run header (:func:`run_header`) in Markdown."""
    lines = [f"# {result.get('command', 'a benchmark run')}", ""]
    for key in ("date", "machine", "numba_threads", "load_average_start", "commit"):
        if key in result:
            lines.append(f"- {key.replace('_', ' ')}: {result[key]}")
    if "versions" in result:
        lines.append("- versions: " + ", ".join(f"{k} {v}" for k, v in result["versions"].items()))
    if "settings" in result:
        lines += ["", *markdown_table(["setting", "value"],
                                      [[k, f"{v}"] for k, v in result["settings"].items()])]
    return lines


def scalar_markdown(result: dict) -> str:
    """A result's scalar values as a table (the default Markdown of :func:`write_result`)."""
    header = {"machine", "numba_threads", "load_average_start", "versions", "commit", "date",
              "command", "settings"}
    rows = [[k, f"{v:.6g}" if isinstance(v, float) else f"{v}"] for k, v in result.items()
            if k not in header and (v is None or isinstance(v, (int, float, str, bool)))]
    return "\n".join(markdown_table(["quantity", "value"], rows)) + "\n" if rows else ""


def _as_json(value):
    """A setting's JSON form where json has none (a dataclass: a prior term)."""
    if dataclasses.is_dataclass(value):
        return dataclasses.asdict(value)
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def write_result(result: dict, output: str | Path,
                 markdown: Callable[[dict], str] = scalar_markdown) -> None:
    """``output``.json (the whole result) and ``output``.md (the run header, then the table
    ``markdown`` makes of the result, also printed)."""
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=_as_json) + "\n")
    table = markdown(result)
    out.with_suffix(".md").write_text("\n".join(header_markdown(result)) + "\n\n" + table)
    print(table)
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


#: The retrieval log's columns of epsilon's parts outside the true cloud and by optical
#: distance from its lit and viewed boundary (cloudct.retrieval.state.SHELL_PARTS).
SHELL_LOG = [f"epsilon_{part.replace(' ', '_')}" for part in SHELL_PARTS]


def error_over_time(result: str | Path, minutes=(5, 10, 15, 30, 60)) -> dict:
    """Iterations, epsilon and delta of a retrieval result file at each of ``minutes`` that
    the run lasted (the last iteration done by then), and at its end, with epsilon's parts
    outside the true cloud and by optical distance where the log has them."""
    ds = xr.load_dataset(result)
    seconds = ds["log_seconds"].values
    parts = [f"log_{name}" for name in ("epsilon", "delta", *SHELL_LOG) if f"log_{name}" in ds]

    def at(i: int) -> dict:
        return {name.removeprefix("log_"): float(ds[name].values[i]) for name in parts}

    marks = {}
    for m in minutes:
        if 60 * m > 1.01 * seconds[-1]:
            break
        done = np.flatnonzero(seconds <= 60 * m)
        if done.size:
            marks[f"{m:g} min"] = {"iteration": int(done[-1] + 1), **at(done[-1])}
    return {"iterations": int(seconds.size), "seconds": float(seconds[-1]),
            "final": at(-1), "over_time": marks}


def error_markdown(result: dict) -> str:
    """The ``runs`` of a retrieval comparison (name -> :func:`error_over_time`) as a table
    of epsilon / delta at each time mark, then its scalar values."""
    runs = result["runs"]
    marks = sorted({m for run in runs.values() for m in run["over_time"]},
                   key=lambda mark: float(mark.split()[0]))  # "5 min"
    rows = [[name, str(run["iterations"]), f"{run['seconds']:.0f}",
             *(f"{run['over_time'][m]['epsilon']:.3f} / {run['over_time'][m]['delta']:+.3f}"
               if m in run["over_time"] else "" for m in marks),
             f"{run['final']['epsilon']:.3f} / {run['final']['delta']:+.3f}"]
            for name, run in runs.items()]
    table = markdown_table(["run", "iterations", "seconds", *marks, "end"], rows)
    return "epsilon / delta\n\n" + "\n".join(table) + "\n\n" + scalar_markdown(result)


def loss_at_the_truth(media: dict, measurements: xr.Dataset, photons: int) -> dict:
    """The loss (Eq. 41, unit weights) of the true extinction rendered under each
    assumption (``media``: name -> the truth as that assumption sees it) against the
    measurements, with each render's and the measurements' own Monte Carlo share of it
    (their squared standard errors): the loss that remains at the truth when an assumption
    is wrong."""
    from cloudct.mc.render import render
    from cloudct.mc.scene import Scene
    from cloudct.retrieval.loss import image_loss

    scene = Scene.from_dataset(measurements)
    measured = measurements["radiance"].values
    out = {"measurement_noise": 0.5 * float(np.sum(measurements["radiance_std_error"]
                                                   .values ** 2))}
    for name, medium in media.items():
        images = render(medium, scene, photons=photons, seed=3, progress=False)
        out[name] = image_loss(images["radiance"].values, measured)[0]
        out[f"{name}_render_noise"] = 0.5 * float(np.sum(images["radiance_std_error"]
                                                         .values ** 2))
    return out


def over_time_markdown(result: dict) -> str:
    """Epsilon and delta at each mark of :func:`error_over_time`'s result, with epsilon's
    parts outside the true cloud and by optical distance where known, as a table."""
    marks = [*result["over_time"].items(), ("end", {"iteration": result["iterations"],
                                                    **result["final"]})]
    shells = [name for name in SHELL_LOG if name in result["final"]]
    rows = [[mark, str(v["iteration"]), f"{v['epsilon']:.3f}", f"{v['delta']:+.3f}",
             *(f"{v[name]:.3f}" for name in shells)] for mark, v in marks]
    header = ["time", "iteration", "epsilon", "delta",
              *(name.removeprefix("epsilon_").replace("_", " ") for name in shells)]
    return "\n".join(markdown_table(header, rows)) + "\n"


def error_figure(runs: dict[str, Path], path: Path, title: str,
                 device: str = "2 CPU cores") -> None:
    """Epsilon and delta against wall time on ``device`` of retrieval results (``cloudct
    retrieve``'s netCDF files), one curve per ``label: file`` of ``runs``, saved to
    ``path``."""
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
        ax.set_xlabel(f"wall time [min], {device}")
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
