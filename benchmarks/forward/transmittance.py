"""Non-exponential transmittance on the seed paper's single cloud (docs/transmittance.md).

Measures, on this machine:

1. the cost of the model: render time of the single cloud without the field, with the
   power law at a = inf everywhere (the exponential limit through the model's branch), and
   with a = 2 everywhere (the walk's per-voxel recursion);
2. forward against backward images under the power law (a = 2): the model is not
   reciprocal (T restarts at 1 at every vertex), so the two estimators estimate different
   images; their view means and their pixel-wise difference in standard errors;
3. the figure: T against optical depth for each family, and the cloud's zenith and oblique
   views rendered exponentially and under the power law;
4. explicit sub-grid media against the model: a periodic slab of 64 x 64 uniform columns
   whose optical depths are gamma distributed (shape a = 2, mean 5), rendered by the
   ordinary exponential engine, against the coarse slab under the power law (a = 2) and
   under exponential transmittance: domain-mean albedo, transmittance and radiance probes
   (cloudct.mc.sensors), the sun at the zenith (its vertical rays stay in their column, so
   the direct beam of the columns is the power law exactly; oblique rays cross many
   columns and average them). The model is an approximation for the diffuse light: this
   reports the differences, it does not test them.

    python -m benchmarks forward.transmittance [--photons N] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from benchmarks.common import REPO, RESULTS, run_header, write_result
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import single_cloud_scene
from cloudct.mc.sensors import domain_means
from cloudct.mc.sun import Sun
from cloudct.medium import cell_edges, optical_medium, with_transmittance
from cloudct.physics.transmittance import GAMMA, LINEAR_MIX, transmittance

FIGURE = REPO / "docs" / "figures" / "transmittance.png"


def with_power_law(medium, a: float):
    """The medium with the gamma (power-law) transmittance of shape ``a`` everywhere."""
    return with_transmittance(medium, "gamma", a)


def timed_render(medium, scene, photons: int, method: str = "forward", repeats: int = 3):
    """The images of the last of ``repeats`` renders and the best wall time."""
    render(medium, scene, photons=64, method=method, batches=2, progress=False)  # compile
    best, images = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        images = render(medium, scene, photons=photons, method=method, seed=1, progress=False)
        best = min(best, time.perf_counter() - start)
    return images, best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photons", type=int, default=1_000_000)
    parser.add_argument("--samples", type=int, default=64, help="backward samples per pixel")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    plain = single_cloud_medium()
    edges = cell_edges(plain)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    results: dict = {**run_header(args), "timings_s": {}}
    images = {}
    for name, medium in (("no field", plain), ("power law a = inf", with_power_law(plain, np.inf)),
                         ("power law a = 2", with_power_law(plain, 2.0))):
        images[name], seconds = timed_render(medium, scene, args.photons)
        results["timings_s"][name] = seconds
        print(f"{name}: {seconds:.2f} s for {args.photons} photons")
    assert np.array_equal(images["no field"].radiance.values,
                          images["power law a = inf"].radiance.values)

    backward, _ = timed_render(with_power_law(plain, 2.0), scene, args.samples, "backward", 1)
    forward = images["power law a = 2"]
    diff = forward.radiance.values - backward.radiance.values
    se = np.hypot(forward.radiance_std_error.values, backward.radiance_std_error.values)
    bright = forward.radiance.values > 0.1 * forward.radiance.values.max()
    view_f, view_b = forward.radiance.values.mean(axis=(1, 2)), backward.radiance.values.mean(
        axis=(1, 2))
    results["forward_vs_backward_a2"] = {
        "view_mean_ratio_forward_over_backward": (view_f / view_b).tolist(),
        "bright_pixels_mean_z": float((diff / se)[bright].mean()),
        "bright_pixels_mean_relative_difference": float(
            (diff[bright] / backward.radiance.values[bright]).mean()),
    }
    exp_views = images["no field"].radiance.values.mean(axis=(1, 2))
    results["power_law_over_exponential_view_means"] = (view_f / exp_views).tolist()
    print(json.dumps(results, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    results["sub_grid_slab"] = sub_grid_slab(args.photons)
    print(json.dumps(results["sub_grid_slab"], indent=1))
    write_result(results, args.out / "transmittance")
    figure(images["no field"], forward)


def sub_grid_slab(photons: int, a: float = 2.0, tau: float = 5.0, n: int = 64) -> dict:
    """Domain means of the explicit sub-grid slab and of the coarse slab under the power
    law and under exponential transmittance (item 4 of the module docstring)."""
    column_tau = np.random.default_rng(11).gamma(a, tau / a, size=(n, n))

    def medium(extinction, nxy):
        axis = (np.arange(nxy) + 0.5) / nxy
        return optical_medium(axis, axis, np.array([0.25, 0.75]), extinction,
                              cloud_albedo=0.99, cloud_g=0.85, air_extinction=0.0)

    coarse = medium(np.full((2, 2, 2), tau), 2)
    cases = {
        "explicit sub-grid columns (exponential engine)":
            medium(np.repeat(column_tau[:, :, None], 2, axis=2), n),
        "coarse, power law a = 2": with_power_law(coarse, a),
        "coarse, exponential": coarse,
    }
    directions = [(0.0, 0.0), (60.0, 0.0), (180.0, 0.0), (120.0, 180.0)]
    out = {}
    for name, m in cases.items():
        means = domain_means(m, directions=directions, sun=Sun(0.0, 0.0), boundary="periodic",
                             photons=photons, seed=3, progress=False)
        out[name] = {key: [float(means[key]), float(means[f"{key}_std_error"])]
                     for key in ("albedo", "transmittance", "transmittance_direct",
                                 "absorptance")}
        out[name]["probes (zenith, azimuth): [radiance, std error]"] = {
            f"{z:g}, {az:g}": [float(v), float(e)] for (z, az), v, e in zip(
                directions, means["radiance"].values, means["radiance_std_error"].values,
                strict=True)}
    return out


def figure(exponential, power_law) -> None:
    """T against optical depth for each family, and two views rendered both ways."""
    tau = np.linspace(0.0, 5.0, 201)
    fig = plt.figure(figsize=(11, 6.4))
    ax = fig.add_subplot(2, 3, (1, 4))
    ax.plot(tau, np.exp(-tau), "k", lw=2, label="exponential")
    for a in (0.5, 2.0, 8.0):
        ax.plot(tau, [transmittance(GAMMA, t, 1.0 / a) for t in tau], label=f"power law a = {a:g}")
    for g in (0.0, 0.5):
        ax.plot(tau, [transmittance(LINEAR_MIX, t, g) for t in tau], "--",
                label=f"linear mix gamma = {g:g}")
    ax.set_xlabel("optical depth tau")
    ax.set_ylabel("transmittance T")
    ax.set_yscale("log")
    ax.set_ylim(1e-3, 1.05)
    ax.legend(fontsize=8)
    ax.set_title("transmittance families", fontsize=10)
    vmax = max(exponential.radiance.values.max(), power_law.radiance.values.max())
    for col, view in ((2, 0), (3, 1)):
        for row, (name, images) in enumerate((("exponential", exponential),
                                              ("power law a = 2", power_law))):
            axis = fig.add_subplot(2, 3, col + 3 * row)
            axis.imshow(images.radiance.values[view], cmap="gray", vmin=0, vmax=vmax)
            axis.set_title(f"{name}, view {view}: mean "
                           f"{images.radiance.values[view].mean():.4f}", fontsize=8)
            axis.axis("off")
    fig.tight_layout()
    fig.savefig(FIGURE, dpi=110)
    print(f"wrote {FIGURE}")


if __name__ == "__main__":
    main()
