"""What limits the single-cloud retrieval: the loss of reference media at a retrieval's stage
settings, and how far the retrieval walks away from the truth when it starts there.

1. Loss of reference media. For each stage of a retrieval run (pixel blocks and image
   photons, read from the ``--run`` result of ``benchmarks/retrieval/single_cloud.py``) the loss
   (seed paper Eq. 41) of: the truth inside the carved hull, the truth averaged over the
   hull's 2x2x2 and 4x4x4 voxel blocks (the best a stage that ties its voxels in blocks
   could do if the loss were minimal at the block average), and the carved start. Each is
   the mean over ``--seeds`` independent renders with its standard error; the loss of an
   image estimate includes its Monte Carlo variance, so the truth's loss is the noise
   floor of the stage. Against them: the run's own loss over its last ``--last``
   iterations of each stage (mean and standard error; fresh photons every iteration) and,
   with ``--retrieved``, the loss of the medium the run retrieved.
2. Drift from the truth: the retrieval (Adam, no recycling) started at the truth inside
   the hull, for ``--drift-minutes`` each at the ``--drift`` settings
   ``PIXEL_BLOCK:VOXEL_BLOCK:PHOTONS:STEP``; epsilon and delta over time.

Each medium's epsilon is split into the extinction outside the true cloud and the error
inside it (:func:`cloudct.retrieval.metrics.epsilon_split`). Usage::

    python -m benchmarks retrieval.limits --run benchmarks/results/retrieval_single_cloud_60min.json
        [--retrieved RETRIEVED.nc] [--seeds 4] [--drift 4:4:200000:2 2:1:400000:0.5]
        [--drift-minutes 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import xarray as xr

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result
from benchmarks.retrieval.single_cloud import measurements_for
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.measurements import coarse_measurements
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.loop import Retrieval, RetrievalConfig
from cloudct.retrieval.loss import image_loss
from cloudct.retrieval.metrics import epsilon_delta, epsilon_split
from cloudct.retrieval.optimizers import block_mean


def mean_and_error(values: list[float]) -> tuple[float, float]:
    v = np.asarray(values, dtype=float)
    return float(v.mean()), float(v.std(ddof=1) / np.sqrt(v.size))


def quality(truth: np.ndarray, beta: np.ndarray) -> dict:
    eps, delta = epsilon_delta(truth, beta)
    return {"epsilon": eps, "delta": delta, **epsilon_split(truth, beta)}


def run_stage_losses(run: dict, last: int) -> list[dict]:
    """Per stage of a retrieval run: its settings and the loss of its last iterations."""
    config, log = RetrievalConfig(**run["config"]), run["log"]
    stage, loss = np.asarray(log["stage"]), np.asarray(log["loss"])
    rows = []
    for i, block in enumerate(config.stages):
        mine = np.nonzero(stage == i)[0]
        if mine.size == 0:
            continue
        tail = mine[-last:]
        rows.append({
            "stage": i, "pixel_block": int(block),
            "photons": config.photons_at(i)[0],  # the images' photons: the loss's noise
            "voxel_block": config.voxel_blocks[i],
            "run_loss": mean_and_error(loss[tail].tolist()),
            "run_quality": {"epsilon": float(log["epsilon"][tail[-1]]),
                            "delta": float(log["delta"][tail[-1]])},
        })
    return rows


def markdown(result: dict) -> str:
    names = list(result["media"])
    media = [[name, f"{q['epsilon']:.3f}", f"{q['delta']:+.3f}",
              f"{q['outside']:.3f}", f"{q['inside']:.3f}"]
             for name, q in result["media"].items()]
    stages = [
        [f"{row['stage']} ({row['pixel_block']}, {row['photons']:,}, {row['voxel_block']})",
         f"{row['run_loss'][0]:.5f} +- {row['run_loss'][1]:.5f} "
         f"({row['run_quality']['epsilon']:.3f})",
         *(f"{row['loss'][n][0]:.5f} +- {row['loss'][n][1]:.5f}" for n in names)]
        for row in result["stages"]
    ]
    lines = [
        f"{result['machine']}, {result['date']}: `{result['command']}`", "",
        "Media (epsilon split: outside the true cloud + inside it):", "",
        *markdown_table(["medium", "epsilon", "delta", "outside", "inside"], media),
        "", f"Loss (mean +- standard error over {result['seeds']} renders) at each stage of "
        f"the run, against the run's own loss over its last {result['last']} iterations:", "",
        *markdown_table(["stage (pixel block, photons, voxel block)", "run (epsilon)", *names],
                        stages),
    ]
    if result["drift"]:
        drift = [
            [str(d["pixel_block"]), str(d["voxel_block"]), f"{d['photons']:,}", str(d["step"]),
             str(len(d["epsilon"])), f"{d['seconds'][-1] / 60:.1f}",
             f"{d['end']['epsilon']:.3f}", f"{d['end']['delta']:+.3f}",
             f"{d['end']['outside']:.3f}", f"{d['end']['inside']:.3f}"]
            for d in result["drift"]
        ]
        lines += ["", "Started at the truth (inside the hull):", "", *markdown_table(
            ["pixel block", "voxel block", "photons", "step", "iterations", "minutes",
             "epsilon at the end", "delta", "outside", "inside"], drift)]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True,
                        help="a benchmarks/retrieval/single_cloud.py result")
    parser.add_argument("--retrieved", default=None,
                        help="the run's retrieved medium (its --medium-output), compared too")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--last", type=int, default=10)
    parser.add_argument("--drift", nargs="*", default=["4:4:200000:2", "2:1:400000:0.5"])
    parser.add_argument("--drift-minutes", type=float, default=3.0)
    parser.add_argument("--measurement-photons", type=int, default=20_000_000)
    parser.add_argument("--work", default=str(WORK))
    parser.add_argument("--output", default=str(RESULTS / "retrieval_limits"))
    args = parser.parse_args()
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 for a standard error")

    truth_medium = single_cloud_medium()
    truth = truth_medium["cloud_extinction"].values
    measurements = measurements_for(truth_medium, args.measurement_photons, Path(args.work))
    run = json.loads(Path(args.run).read_text())
    # the run's carved start; runs before the excess profile record "carved hull" alone
    profile = "excess" if "excess profile" in run.get("start", "") else "constant"
    carved = carve(measurements, truth_medium, profile=profile)
    start = initial_medium(carved, truth_medium)
    hull = carved["hull"].values > 0
    inside = np.where(hull, truth, 0.0)
    media = {
        "truth in hull": inside,
        "truth, 2x2x2 blocks": block_mean(inside, hull, 2),
        "truth, 4x4x4 blocks": block_mean(inside, hull, 4),
        "carved start": start["cloud_extinction"].values,
    }
    if args.retrieved is not None:
        media["retrieved"] = xr.load_dataset(args.retrieved)["cloud_extinction"].values
    result = {**run_header(args), "seeds": args.seeds, "last": args.last,
              "media": {name: quality(truth, beta) for name, beta in media.items()}}

    result["run"] = {"file": args.run, "config": run["config"]}
    stages = run_stage_losses(run, args.last)
    for row in stages:
        data = coarse_measurements(measurements, row["pixel_block"])
        scene = Scene.from_dataset(data)
        row["loss"] = {}
        for name, beta in media.items():
            medium = truth_medium.copy(deep=True)
            medium["cloud_extinction"].values = beta
            losses = []
            for seed in range(args.seeds):
                images = render(medium, scene, photons=row["photons"], seed=1000 + seed,
                                progress=False)
                losses.append(image_loss(images["radiance"].values,
                                         data["radiance"].values)[0])
            row["loss"][name] = mean_and_error(losses)
            print(row["stage"], name, row["loss"][name], flush=True)
    result["stages"] = stages

    result["drift"] = []
    at_truth = truth_medium.copy(deep=True)
    at_truth["cloud_extinction"].values = inside
    for spec in args.drift:
        pixel_block, voxel_block, photons, step = spec.split(":")
        config = RetrievalConfig(
            iterations=10**9, photons=int(photons), step=float(step), stages=(int(pixel_block),),
            stage_photons=(1.0,), voxel_blocks=(int(voxel_block),), gradient_smoothing=(0.0,),
            image_photons=(1.0,), step_decay=1.0, checkpoint_every=10**9,
            time_limit=60.0 * args.drift_minutes,
        )
        drift = Retrieval(measurements, at_truth, config, mask=hull, truth=truth_medium)
        drift.run(progress=False)
        log = drift.state.log
        result["drift"].append({
            "pixel_block": int(pixel_block), "voxel_block": int(voxel_block),
            "photons": int(photons), "step": float(step),
            **{k: log[k] for k in ("loss", "epsilon", "delta", "seconds")},
            "end": quality(truth, drift.state.extinction),
        })
        print(spec, result["drift"][-1]["end"], flush=True)
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
