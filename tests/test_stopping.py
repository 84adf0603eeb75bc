"""A retrieval stopped by SIGTERM or Ctrl-C ends at the end of its iteration with a
checkpoint, says how to go on, and goes on bitwise as if it had never stopped."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import xarray as xr
from test_config import SMALL, inputs  # noqa: F401 - the fixture
from test_retrieval import initial_guess
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.cli import main
from cloudct.mc.render import render
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.stopping import RunStopped

CONFIG = RetrievalConfig(iterations=4, photons=1500, seed=5, priors=(), checkpoint_every=100)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_ends_the_run_after_its_iteration_and_it_resumes_bitwise(tmp_path, signum):
    measurements = render(gradient_medium(), gradient_scene(), photons=400_000, seed=77,
                          progress=False)
    straight = Retrieval(measurements, initial_guess(), CONFIG)
    straight.run(progress=False)
    before = signal.getsignal(signum)
    run = Retrieval(measurements, initial_guess(), CONFIG)
    step = run.step

    def step_then_signal() -> dict:  # the signal lands inside iteration 2
        if run.state.iteration == 1:
            os.kill(os.getpid(), signum)
        return step()

    run.step = step_then_signal
    with pytest.raises(RunStopped, match=f"stopped by {signum.name} after iteration 2; "
                       "checkpoint") as stop:
        run.run(checkpoint=tmp_path / "ck.nc", progress=False)
    assert (stop.value.signum, stop.value.iteration) == (signum, 2)
    assert signal.getsignal(signum) == before  # the handlers of before are back
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess())
    assert resumed.state.iteration == 2
    resumed.run(progress=False)
    np.testing.assert_array_equal(resumed.state.extinction, straight.state.extinction)
    np.testing.assert_array_equal(resumed.state.log["loss"], straight.state.log["loss"])


def test_sigterm_stops_cloudct_retrieve_with_a_checkpoint_and_the_command_to_go_on(
        tmp_path, inputs):  # noqa: F811
    out = tmp_path / "r.nc"
    checkpoint = tmp_path / "r.checkpoint.nc"
    argv = ["retrieve", *inputs, *SMALL, "--photons", "20000", "--iterations", "8",
            "--checkpoint-every", "1", "-o", str(out)]
    cloudct = "import sys; from cloudct.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", cloudct, *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not checkpoint.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, err
    last = err.strip().splitlines()[-1]
    assert "cloudct retrieve: stopped by SIGTERM after iteration " in last
    command = last.split("to go on from there: cloudct ")[1]
    assert command == shlex.join([*argv, "--resume"]) and not out.exists()
    stopped_at = xr.load_dataset(checkpoint).sizes["iteration"]
    assert 1 <= stopped_at < 8
    assert main(shlex.split(command)) == 0
    straight = tmp_path / "straight.nc"
    assert main([*argv[:-1], str(straight), "--checkpoint", str(tmp_path / "s.ck.nc")]) == 0
    np.testing.assert_array_equal(xr.load_dataset(out)["cloud_extinction"].values,
                                  xr.load_dataset(straight)["cloud_extinction"].values)


def test_a_run_resumed_on_another_back_end_says_so(tmp_path, caplog):
    measurements = render(gradient_medium(), gradient_scene(), photons=100_000, seed=77,
                          progress=False)
    config = replace(CONFIG, iterations=1)
    Retrieval(measurements, initial_guess(), config).run(checkpoint=tmp_path / "ck.nc",
                                                         progress=False)
    ck = xr.load_dataset(tmp_path / "ck.nc")
    ck.attrs["backend"] = "cuda"  # as a GPU run's
    ck.to_netcdf(tmp_path / "gpu.nc")
    with caplog.at_level("INFO", logger="cloudct"):
        resumed = Retrieval.resume(tmp_path / "gpu.nc", measurements, initial_guess(),
                                   iterations=2)
    assert resumed.backend == "cpu" and resumed.state.iteration == 1
    assert "resumed on the cpu back end from a checkpoint traced on cuda" in caplog.text
