"""The memory a render or a gradient needs at its peak, known before the work: the estimate
against a measured peak, and the refusal where it cannot fit."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest
from test_config import SMALL, inputs  # noqa: F401 - the fixture

from cloudct.cli import main
from cloudct.mc import memory

PEAK = """
import json
import numpy as np
from data_synth.synthetic_cloud import synthetic_cloud
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.memory import peak_bytes, resident_bytes
from cloudct.mc.scene import single_cloud_scene_of
from cloudct.optics import to_optical

medium = to_optical(synthetic_cloud(90, 90, 40, seed=1))
scene = single_cloud_scene_of(medium)
residual = np.random.default_rng(0).normal(size=(9, 76, 76))
# the kernels compiled or loaded first (compiling has its own peak), on the same arrays
score_function_gradient(medium, scene, residual, photons=64, batches=32, progress=False)
before = resident_bytes()
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")  # the peak resident memory from here on (Linux)
score_function_gradient(medium, scene, residual, photons=500, batches=32, progress=False)
status = open("/proc/self/status").read()
peak = int(status.split("VmHWM:")[1].split()[0]) * 1024
print("RESULT " + json.dumps({"measured": peak - before, "estimate": peak_bytes(
    medium["cloud_extinction"].size, residual.size, 32, gradient=True)}))
"""


def test_the_estimate_of_a_gradient_is_its_measured_peak_within_a_fifth():
    """90 x 90 x 40 voxels, 32 batches: the per-batch gradients are 2 x 83 MB."""
    proc = subprocess.run([sys.executable, "-c", PEAK], capture_output=True, text=True,
                          timeout=600, check=True)
    result = json.loads(proc.stdout.split("RESULT ")[1])
    assert result["measured"] <= result["estimate"] <= 1.2 * result["measured"], result


def test_a_run_that_cannot_fit_is_refused_in_one_line(tmp_path, inputs, capsys,  # noqa: F811
                                                      monkeypatch):
    monkeypatch.setattr(memory, "available_bytes", lambda: 2**10)  # 1 KiB free
    out = tmp_path / "r.nc"
    assert main(["retrieve", *inputs, *SMALL, "--iterations", "1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert re.fullmatch(r"cloudct retrieve: error: retrieve: about \d+ KiB of memory at its "
                        r"peak, beyond this process's [\d.]+ GiB, but only 1 KiB is free: use a "
                        r"coarser grid, or a machine with more memory", err), err
    assert not out.exists()
    monkeypatch.setattr(memory, "available_bytes", lambda: 2**40)
    assert main(["retrieve", *inputs, *SMALL, "--iterations", "1", "-o", str(out)]) == 0
    assert re.search(r"^retrieve: about \d+ KiB of memory at its peak, beyond this process's "
                     r"[\d.]+ GiB; 1024\.00 GiB free$", capsys.readouterr().out, re.M)


@pytest.mark.parametrize("gradient, per_batch", [(True, 1000), (False, 50)])
def test_the_estimate_counts_its_per_batch_arrays_and_the_grid(gradient, per_batch):
    expected = 8 * (memory.PEAK_COPIES * 32 * per_batch + memory.GRID_ARRAYS * 1000)
    assert memory.peak_bytes(1000, 50, 32, gradient) == expected
