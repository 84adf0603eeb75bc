"""Retrieval reports: epsilon/delta (seed paper Eq. 54), their history, the loss curve,
slices and a scatter plot of retrieved vs true extinction, where the error lives by optical
distance from the cloud's lit and viewed boundary, and re-rendered vs measured images, as
PNG figures plus a Markdown summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.output_files import save_figure
from cloudct.retrieval.config_file import config_from_json, config_to_toml
from cloudct.retrieval.metrics import (
    SHELLS,
    epsilon_by_shell,
    epsilon_delta,
    epsilon_split,
    shell_names,
)
from cloudct.retrieval.priors import as_prior, prior_text
from cloudct.retrieval.report_figures import (
    Curve,
    Panel,
    curves_figure,
    images_figure,
    pyplot,
    slices_figure,
)

#: Photons of the report's re-render of a result, at most.
RENDER_PHOTONS = 1_000_000


def render_photon_count(measurements: xr.Dataset, render_photons: int | None = None) -> int:
    """The photons of a report's re-render of a result to compare with ``measurements``:
    ``render_photons`` where given, else :data:`RENDER_PHOTONS` or the measurements' own
    photons (attribute ``photons``) where they record fewer: a re-render more precise than
    the images it is compared to adds nothing."""
    if render_photons is not None:
        return int(render_photons)
    return int(min(RENDER_PHOTONS, measurements.attrs.get("photons", RENDER_PHOTONS)))


def image_difference(measured: np.ndarray, rendered: np.ndarray) -> float:
    """The relative L1 difference of re-rendered and measured images, sum |I - m| / sum |m|
    over the measured pixels (NaN pixels, masked, are left out)."""
    return float(np.nansum(np.abs(rendered - measured)) / np.nansum(np.abs(measured)))


def write_report(
    result: xr.Dataset,
    directory: str | Path,
    *,
    truth: xr.Dataset | None = None,
    measurements: xr.Dataset | None = None,
    render_photons: int | None = None,
    backend: str = "cpu",
) -> Path:
    """Write figures and ``summary.md`` for a retrieval result; returns the summary path.
    With ``measurements``, the result is re-rendered (``render_photons`` photons; default
    :data:`RENDER_PHOTONS`, or the measurements' own photons where they record fewer: a
    re-render more precise than the images it is compared to adds nothing) on
    ``backend`` (:mod:`cloudct.mc.backend`) for the images' comparison; with the ``truth``
    as well, epsilon is split by the true cloud's optical distance from its lit and viewed
    boundary in the measurements' scene
    (:func:`~cloudct.retrieval.metrics.epsilon_by_shell`, ``shells.png``)."""
    plt = pyplot()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# cloudct retrieval report", ""]
    config = json.loads(result.attrs.get("config", "{}"))
    lines += [
        f"- run id: `{result.attrs.get('run_id', '?')}`",
        f"- iterations: {result.attrs.get('iterations_done', '?')}, wall time "
        f"{float(result.attrs.get('elapsed_s', np.nan)):.0f} s ({_compiling_text(result)}), "
        "final stage "
        f"{result.attrs.get('stage', '?')}, on {result.attrs.get('device', 'an unrecorded device')}"
        f" (back end {result.attrs.get('backend', '?')})",
        "- settings: [the run's configuration](#configuration) below",
        f"- priors: {priors_text(config)}",
        f"- transmittance: retrieved under {result.attrs.get('transmittance', 'exponential')}"
        f", the measurements made under {result.attrs.get('measurement_transmittance', '?')}"
        " (docs/transmittance.md)",
    ]
    if "log_gradient_seconds" in result:
        stages = result["log_stage"].values.astype(int)
        names = config.get("estimator") or ["score"] * (stages.max() + 1)
        for stage in np.unique(stages):
            seconds = result["log_gradient_seconds"].values[stages == stage]
            seconds = seconds[np.isfinite(seconds)]
            cost = (f"the gradient {seconds.mean():.2f} s per iteration" if seconds.size
                    else "replayed")
            lines.append(f"- stage {stage}: gradient estimator {names[stage]}"
                         f" ({config.get('pixel_sampling', 'uniform')} pixels), {cost}")
    lines.append("")
    beta = result["cloud_extinction"].values
    if "log_loss" in result:
        curves_figure(result["log_seconds"].values,
                      [Panel([Curve(None, result["log_loss"].values)], "loss (Eq. 41)",
                             "loss (stages differ in pixel count)", log=True)],
                      "wall time [s]", out / "loss.png")
        lines += ["![loss](loss.png)", ""]
    if truth is not None:
        true_beta = truth["cloud_extinction"].values
        eps, delta = epsilon_delta(true_beta, beta)
        split = epsilon_split(true_beta, beta)
        lines += ["## Error against the truth (Eq. 54)", "",
                  "| medium | epsilon | delta |", "| --- | --- | --- |",
                  f"| last iterate | {eps:.1%} | {delta:+.1%} |"]
        if "cloud_extinction_average" in result:
            eps_a, delta_a = epsilon_delta(true_beta, result["cloud_extinction_average"].values)
            lines.append(f"| {config.get('averaging')} average of the iterates "
                         f"(cloud_extinction_average) | {eps_a:.1%} | {delta_a:+.1%} |")
        lines += ["",
                  "Where epsilon comes from (each relative to the true cloud's mass):", "",
                  "| outside the true cloud | inside the cloud | retrieved mass in the cloud |",
                  "| --- | --- | --- |",
                  f"| {split['outside']:.1%} | {split['inside']:.1%} | "
                  f"{split['cloud_mass']:.1%} |", ""]
        if "log_epsilon" in result and np.isfinite(result["log_epsilon"].values).any():
            curves = [Curve("epsilon", result["log_epsilon"].values),
                      Curve("delta", result["log_delta"].values)]
            if "log_epsilon_average" in result and np.isfinite(
                result["log_epsilon_average"].values
            ).any():
                curves.append(Curve("epsilon of the iterate average",
                                    result["log_epsilon_average"].values, "--"))
            curves_figure(result["log_seconds"].values, [Panel(curves, zero=True)],
                          "wall time [s]", out / "epsilon_delta.png")
            lines += ["![epsilon and delta](epsilon_delta.png)", ""]
        slices_figure([("true", true_beta), ("retrieved", beta)], result["z"].values,
                      "cloud extinction [1/km]", out / "slices.png")
        fig, ax = plt.subplots(figsize=(4.2, 4))
        cloudy = (true_beta > 0) | (beta > 0)
        ax.scatter(true_beta[cloudy], beta[cloudy], s=3, alpha=0.4)
        top = max(true_beta.max(), beta.max())
        ax.plot([0, top], [0, top], "k--", lw=0.8)
        ax.set_xlabel("true extinction [1/km]")
        ax.set_ylabel("retrieved extinction [1/km]")
        fig.tight_layout()
        save_figure(fig, out / "scatter.png", dpi=110)
        plt.close(fig)
        lines += ["![slices](slices.png)", "", "![scatter](scatter.png)", ""]
        if measurements is not None:
            lines += _shell_lines(plt, truth, beta, measurements, out / "shells.png")
    if measurements is not None:
        from cloudct.mc.render import render
        from cloudct.mc.scene import Scene

        render_photons = render_photon_count(measurements, render_photons)
        images = render(result, Scene.from_dataset(measurements), photons=render_photons,
                        progress=False, backend=backend)
        rendered = images["radiance"].values
        measured = measurements["radiance"].values  # NaN pixels (masked) are left out
        images_figure([("measured", measured), ("retrieved", rendered)], out / "images.png")
        lines += ["## Re-rendered vs measured images", "",
                  f"Relative L1 image difference: {image_difference(measured, rendered):.1%} "
                  f"(re-rendered with {render_photons} photons on the "
                  f"{images.attrs['backend']} back end; their Monte Carlo noise is part of "
                  "it).", "",
                  "![images](images.png)", ""]
    decisions = json.loads(result.attrs.get("decisions", "[]"))
    if decisions:
        lines += ["## What the run changed on its own", "",
                  "| after iteration | change | why |", "| --- | --- | --- |",
                  *(f"| {d['iteration']} | {d['what']} | {d['why']} |" for d in decisions), ""]
    if "log_step" in result and np.isfinite(result["log_step"].values).any():
        _schedule_figure(plt, result, decisions, out / "schedule.png")
        lines += ["![step and photons against time](schedule.png)", ""]
    lines += configuration_lines(result)
    summary = out / "summary.md"
    summary.write_text("\n".join(lines))
    return summary


def _shell_lines(plt, truth: xr.Dataset, beta: np.ndarray, measurements: xr.Dataset,
                path: Path) -> list[str]:
    """The summary's section on where epsilon lives by the true cloud's optical distance d
    from its lit and viewed boundary (:func:`cloudct.mc.visibility.boundary_optical_distance`
    in the measurements' scene; shells of :data:`cloudct.retrieval.metrics.SHELLS`), with
    its figure at ``path``."""
    from cloudct.mc.scene import Scene
    from cloudct.mc.visibility import boundary_optical_distance

    true_beta = truth["cloud_extinction"].values
    distance = boundary_optical_distance(truth, Scene.from_dataset(measurements))
    parts = epsilon_by_shell(true_beta, beta, distance)
    names = shell_names()
    eps = epsilon_delta(true_beta, beta)[0]
    retrieved = epsilon_split(true_beta, beta)["cloud_mass"]

    def ratio(value: float) -> str:
        return f"{value:.2f}" if np.isfinite(value) else "-"

    _shells_figure(plt, parts, names, path)
    return [
        "## Where the error lives: by optical distance from the lit and viewed boundary", "",
        "d: the true cloud's optical depth from a voxel's centre towards the sun plus that "
        "towards the nearest camera (the veiled core, beyond about 5, is barely seen by the "
        "images: there the prior speaks; docs/guide.md). Each part of epsilon and each mass "
        "share is relative to the true cloud's mass; the parts sum to epsilon.", "",
        "| voxels | share of the true mass | part of epsilon | retrieved / true mass |",
        "| --- | --- | --- | --- |",
        f"| outside the true cloud | - | {parts['outside']:.1%} | - |",
        *(f"| true cloud, d {name} | {parts[name + ': true mass']:.1%} | {parts[name]:.1%} "
          f"| {ratio(parts[name + ': retrieved/true'])} |" for name in names),
        f"| all | 100.0% | {eps:.1%} | {ratio(retrieved)} |", "",
        "![epsilon by optical distance](shells.png)", ""]


def _shells_figure(plt, parts: dict[str, float], names: list[str], path: Path) -> None:
    """Left: each part of epsilon beside the share of the true mass it concerns; right: the
    retrieved-to-true mass ratio per shell (1: the mass is right)."""
    rows = ["outside", *names]
    x = np.arange(len(rows))
    fig, (left, right) = plt.subplots(1, 2, figsize=(8.5, 3.4),
                                      gridspec_kw={"width_ratios": [len(rows), len(names)]})
    left.bar(x - 0.2, [parts[r] for r in rows], 0.4, label="part of epsilon")
    left.bar(x[1:] + 0.2, [parts[f"{n}: true mass"] for n in names], 0.4, color="0.7",
             label="share of the true mass")
    left.set_xticks(x, ["outside\nthe cloud", *(f"d {n}" for n in names)], fontsize=8)
    left.set_ylabel("relative to the true mass")
    left.set_title(f"epsilon {sum(parts[r] for r in rows):.1%}: the sum of the blue bars",
                   fontsize=9)
    left.legend(fontsize=8)
    ratios = [parts[f"{n}: retrieved/true"] for n in names]
    right.bar(np.arange(len(names)), np.nan_to_num(ratios), 0.6, color="tab:orange")
    right.axhline(1.0, color="k", lw=0.8, ls="--")
    right.set_xticks(np.arange(len(names)), [f"d {n}" for n in names], fontsize=8)
    right.set_ylabel("retrieved / true mass")
    fig.suptitle(f"d: optical distance from the lit and viewed boundary (shells at "
                 f"{', '.join(f'{e:g}' for e in SHELLS)})", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def _compiling_text(result: xr.Dataset) -> str:
    """How long the run's iterations compiled kernels or loaded them from the cache."""
    if "log_compile_seconds" not in result:
        return "compile time not recorded"
    seconds = np.nansum(result["log_compile_seconds"].values)
    ahead = float(result.attrs.get("compile_ahead_s", 0.0))
    text = f"{seconds:.0f} s of it compiling or loading kernels"
    return text + (f"; {ahead:.0f} s compiling ahead, beside the loading and carving"
                   if ahead > 0 else "")


def priors_text(config: dict) -> str:
    """A result's prior terms (``config``: its attribute ``config`` read as JSON) as
    ``--prior`` writes them (cloudct.retrieval.priors; a run from before the terms: its L1
    weight)."""
    if "priors" not in config:
        return f"l1={config.get('sparsity', 0.0):g} (the L1 prior alone)"
    return " ".join(prior_text(as_prior(p)) for p in config["priors"]) or "none"


def configuration_lines(result: xr.Dataset) -> list[str]:
    """The summary's closing section: the run's settings as TOML (:func:`stored_config`)."""
    return ["## Configuration", "",
            "The run's settings (`cloudct retrieve --config` of this text, or of the result "
            "file, re-runs it; docs/retrieval_config.md):", "",
            "```toml", stored_config(result).rstrip("\n"), "```", ""]


def stored_config(result: xr.Dataset) -> str:
    """The TOML text of a result's configuration (attribute ``config_toml``; results from
    before it: converted from the JSON attribute ``config``)."""
    if "config_toml" in result.attrs:
        return str(result.attrs["config_toml"])
    if "config" in result.attrs:
        return config_to_toml(config_from_json(result.attrs["config"]))
    return "# (the result holds no configuration)\n"


def _schedule_figure(plt, result: xr.Dataset, decisions: list[dict], path: Path) -> None:
    """The step and the photons per iteration against wall time, the run's decisions
    marked."""
    seconds = result["log_seconds"].values
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(5, 4.5), sharex=True)
    top.semilogy(seconds, result["log_step"].values, drawstyle="steps-post")
    top.set_ylabel("step [1/km]")
    bottom.semilogy(seconds, result["log_photons"].values, drawstyle="steps-post")
    bottom.set_ylabel("photons per iteration")
    bottom.set_xlabel("wall time [s]")
    for d in decisions:
        at = seconds[min(int(d["iteration"]), seconds.size) - 1]
        for ax in (top, bottom):
            ax.axvline(at, color="0.7", lw=0.6, zorder=0)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)

