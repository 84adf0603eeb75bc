"""Compiling ahead (cloudct.retrieval.warm_up): which tasks a retrieval's settings need,
the markers that say a task ran, the background processes and the command lines."""

from __future__ import annotations

import pytest
import xarray as xr
from test_config import SMALL, inputs  # noqa: F401 - the fixture

from cloudct.cli import main
from cloudct.jit_cache import compile_clock
from cloudct.mc.gradient import ESTIMATORS
from cloudct.retrieval import warm_up
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.warm_up import AHEAD_SWITCH, BackgroundWarmUp, pending, run_task, tasks_for


def test_the_tasks_of_a_retrieval_follow_its_estimators_images_and_recycling():
    default = RetrievalConfig()
    assert tasks_for(default, carving=False) == ["render:forward", "gradient:sm"]
    # the carving's fit renders forward in the run's own process
    assert tasks_for(default, carving=True) == ["gradient:sm"]
    staged = RetrievalConfig(stages=(2, 1), stage_photons=(1.0, 1.0), image_photons=(1.0, 1.0),
                             estimator=("drt", "drt"), image_method="combined")
    assert tasks_for(staged, carving=True) == ["render:combined", "gradient:drt"]
    recycled = RetrievalConfig(recycling="fixed")
    assert tasks_for(recycled, carving=True) == ["gradient:score", "recycling"]
    assert {t for t in warm_up.TASKS if t.startswith("gradient:")} == {
        f"gradient:{e}" for e in ESTIMATORS}


def test_a_task_leaves_its_kernels_and_a_marker_until_cloudct_changes(tmp_path, monkeypatch):
    monkeypatch.setattr(warm_up, "kernel_cache_dir", lambda: tmp_path)
    assert pending(["render:forward"], "cpu") == ["render:forward"]
    run_task("render:forward")
    assert pending(["render:forward", "gradient:drt"], "cpu") == ["gradient:drt"]
    assert pending(["render:forward"], "cpu", optics="mie") == ["render:forward"]
    with compile_clock() as clock:  # the same kernels again: loaded, nothing compiled
        run_task("render:forward")
    assert clock.seconds < 5.0
    monkeypatch.setattr(warm_up, "source_stamp", lambda path: "another source")
    assert pending(["render:forward"], "cpu") == ["render:forward"]
    with pytest.raises(ValueError, match="warm-up task must be one of"):
        run_task("render:sideways")


def test_a_background_task_that_fails_is_a_warning_and_the_switch_turns_it_off(monkeypatch):
    monkeypatch.setenv(AHEAD_SWITCH, "1")
    ahead = BackgroundWarmUp(["render:sideways"], backend="cpu")  # fails in its process
    assert ahead.tasks == ["render:sideways"]
    with pytest.warns(RuntimeWarning, match=r"compiling ahead \(render:sideways\) failed.*"
                      "must be one of"):
        assert ahead.wait() > 0.0
    monkeypatch.setenv(AHEAD_SWITCH, "0")
    off = BackgroundWarmUp(["render:sideways"], backend="cpu")
    assert off.tasks == [] and off.wait() == 0.0


def test_retrieve_compiles_ahead_what_the_cache_lacks_and_says_so(tmp_path, inputs, capsys,  # noqa: F811
                                                                  monkeypatch):
    monkeypatch.setenv(AHEAD_SWITCH, "1")
    monkeypatch.setattr(warm_up, "kernel_cache_dir", lambda: tmp_path / "cache")  # no markers
    out = tmp_path / "r.nc"
    assert main(["retrieve", *inputs, *SMALL, "--iterations", "1", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    # the start is a file, not a carved hull: the forward render compiles ahead too
    assert "compiling ahead, in other processes: render:forward, gradient:sm\n" in printed
    assert "compiled ahead in" in printed and out.exists()
    assert xr.load_dataset(out).attrs["compile_ahead_s"] > 0.0


def test_cache_warm_runs_the_tasks_named(capsys):
    assert main(["cache", "--warm", "render:forward", "--backend", "cpu", "--jobs", "1"]) == 0
    printed = capsys.readouterr().out
    assert "render:forward: " in printed and "the kernels of 1 tasks are in" in printed
    with pytest.raises(SystemExit) as stop:
        main(["cache", "--warm", "render:sideways"])
    assert stop.value.code == 2
