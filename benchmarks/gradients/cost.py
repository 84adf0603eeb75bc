"""Cost of the score-function gradient relative to a forward render of the same paths.

Single-cloud scene (nine 76x76 views); both runs trace the same photons (same seed); the
gradient's residual weights are random fixed numbers (every pixel non-zero, the worst
case: pixels with zero weight are skipped). JIT compilation is excluded. Usage::

    python -m benchmarks gradients.cost [--photons 400000] [--repeats 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result


def main() -> None:
    from cloudct.mc.gradient import score_function_gradient
    from cloudct.mc.render import render, single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=400_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", default=str(RESULTS / "gradient_cost"))
    args = parser.parse_args()
    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    residual = np.random.default_rng(0).normal(size=(9, 76, 76))
    render(medium, scene, photons=64, progress=False)
    score_function_gradient(medium, scene, residual, photons=64, progress=False)
    rows = []
    for r in range(args.repeats):
        images = render(medium, scene, photons=args.photons, seed=r, progress=False)
        _, _, info = score_function_gradient(
            medium, scene, residual, photons=args.photons, seed=r, progress=False
        )
        rows.append({"render_s": images.attrs["wall_time"], "gradient_s": info["wall_time"],
                     "ratio": info["wall_time"] / images.attrs["wall_time"]})
        print(rows[-1], flush=True)
    result = {**run_header(args), "runs": rows,
              "median_ratio": float(np.median([r["ratio"] for r in rows]))}
    write_result(result, args.output)


if __name__ == "__main__":
    main()
