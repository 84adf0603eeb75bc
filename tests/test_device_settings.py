"""The chain on the device that is there: every command takes --backend cpu|cuda|auto and
records where it ran, and photons = "auto" fits the photons per iteration to the device."""

from __future__ import annotations

import json
import re
from contextlib import contextmanager

import numpy as np
import pytest
import xarray as xr
from test_retrieval import initial_guess
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.cli import main
from cloudct.mc.backend import cuda_unavailable_reason
from cloudct.mc.render import render
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.photon_budget import MOST_UP, rescaled_count, start_count
from cloudct.retrieval.report import write_report

NO_GPU = cuda_unavailable_reason()


def test_the_count_is_rescaled_towards_the_target_until_it_settles():
    assert rescaled_count(50_000, 9.0, 10.0) is None  # within 2/3 .. 3/2 of the target
    assert rescaled_count(50_000, 14.9, 10.0) is None
    assert rescaled_count(50_000, 1.0, 10.0) == 500_000
    assert rescaled_count(50_000, 3.0, 10.0) == 170_000  # 166,667 to two digits
    assert rescaled_count(50_000, 0.01, 10.0) == int(50_000 * MOST_UP)
    assert rescaled_count(50_000, 100.0, 10.0) == 12_000  # 50,000 / 4 to two digits
    assert rescaled_count(3, 100.0, 10.0) == 1  # never below one path
    assert start_count("cuda") > start_count("cpu") == start_count("somewhere else")


@pytest.fixture(scope="module")
def measurements():
    return render(gradient_medium(), gradient_scene(), photons=400_000, seed=77,
                  progress=False)


class DeviceClock:
    """A fake wall clock for a run: an iteration tracing n photons (the images' and the
    gradient's) takes n / ``rate`` seconds, the first ``slow`` iterations ``factor`` times
    longer (a machine busy with something else, or costs of a first iteration)."""

    def __init__(self, run: Retrieval, rate: float, slow: int = 0, factor: float = 1.0):
        self.run, self.rate, self.slow, self.factor = run, rate, slow, factor
        self.now, self.calls = 0.0, 0

    def __call__(self) -> float:
        self.calls += 1
        if self.calls % 2 == 0:  # the end of an iteration (Retrieval.step reads it twice)
            s = self.run.state
            traced = sum(self.run.config.photons_at(s.stage, s.photons))
            self.now += traced / self.rate * (self.factor if s.iteration < self.slow else 1.0)
        return self.now


def auto_run(measurements, monkeypatch, slow: int, factor: float, compiling: float = 0.0
             ) -> Retrieval:
    """A retrieval of photons "auto" aiming at 1-s iterations from 5,000 paths (a small
    count keeps the test's iterations short) on the fake clock of a device that traces
    60,000 photons a second (:class:`DeviceClock`), whose first iteration spends the
    fraction ``compiling`` of its time compiling (none otherwise: the kernels the test
    session compiled for real are left out)."""
    config = RetrievalConfig(photons="auto", iteration_seconds=1.0, stages=(1,))
    run = Retrieval(measurements, initial_guess(), config)
    run.state.photons = 5000
    run.clock = DeviceClock(run, 60_000.0, slow, factor)

    class FakeCompileClock:  # read once the iteration's time is known
        @property
        def seconds(self) -> float:  # the first iteration's starts at 0 on the fake clock
            return compiling * run.clock.now if run.state.iteration == 0 else 0.0

    @contextmanager
    def fake_compile_clock():
        yield FakeCompileClock()

    monkeypatch.setattr("cloudct.retrieval.loop.compile_clock", fake_compile_clock)
    return run


def test_auto_photons_refit_when_slow_first_iterations_sized_them(measurements, monkeypatch):
    """The first two iterations 10x slow: the count settles 10x too low (2,000 where the
    device traces 20,000 gradient paths, 60,000 photons with the images', per second), and
    the median of the next three iterations' times puts it right."""
    run = auto_run(measurements, monkeypatch, slow=2, factor=10.0)
    for _ in range(7):
        run.step()
    assert run.state.log["photons"] == [15_000.0] + [6000.0] * 4 + [60_000.0] * 2
    assert [d["what"] for d in run.state.decisions] == [
        "photons 5000 -> 2000", "photons settled at 2000",
        "photons 2000 -> 20000 (settled at 20000)"]
    assert [d["iteration"] for d in run.state.decisions] == [1, 2, 5]
    assert run.state.photons_base == 20_000


def test_auto_photons_size_on_tracing_time_without_the_compiling(measurements, monkeypatch):
    """A first iteration 10x slow because it compiled (9/10 of its time in numba's compiler
    lock): the count is sized on the rest, right at once; the log keeps the compiling."""
    run = auto_run(measurements, monkeypatch, slow=1, factor=10.0, compiling=0.9)
    for _ in range(3):
        run.step()
    assert run.state.log["photons"] == [15_000.0, 60_000.0, 60_000.0]
    assert run.state.log["compile_seconds"] == pytest.approx([2.25, 0.0, 0.0])
    assert [d["what"] for d in run.state.decisions] == [
        "photons 5000 -> 20000", "photons settled at 20000"]


def test_a_fixed_count_is_never_refitted(measurements):
    fixed = Retrieval(measurements, initial_guess(), RetrievalConfig(photons=7000))
    for seconds in (1.0, 100.0, 1.0, 1.0):
        fixed._schedule(seconds)
    assert (fixed.state.photons, fixed.state.decisions) == (7000, [])


def test_an_auto_run_traces_the_counts_it_chose_and_resumes_with_them(tmp_path, measurements):
    # a tiny problem's iterations take far less than the target: the count grows
    config = RetrievalConfig(photons="auto", iteration_seconds=1e6, iterations=2,
                             stages=(1,), checkpoint_every=1)
    run = Retrieval(measurements, initial_guess(), config)
    run.state.photons = 1000  # keep the test's iterations short
    result = run.run(checkpoint=tmp_path / "ck.nc", progress=False)
    photons = result["log_photons"].values  # images' (x2) and gradient's photons
    assert list(photons) == [3 * 1000, 3 * 16_000]
    compiling = result["log_compile_seconds"].values
    assert result["log_compile_seconds"].attrs["units"] == "s"
    assert np.all((compiling >= 0.0) & (compiling <= np.diff(result["log_seconds"], prepend=0)))
    decisions = json.loads(result.attrs["decisions"])
    assert [d["iteration"] for d in decisions] == [1, 2]
    assert result.attrs["photons_now"] == 260_000 and result.attrs["photons_settled"] == 0
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess())
    assert (resumed.state.photons, resumed.state.decisions) == (260_000, decisions)
    summary = write_report(result, tmp_path / "report").read_text()
    assert "## What the run changed on its own" in summary
    assert "| 1 | photons 1000 -> 16000 | photons auto:" in summary


@pytest.mark.skipif(NO_GPU is None, reason="a GPU is here: auto chooses it")
def test_every_command_runs_where_auto_finds_and_records_it(tmp_path, capsys):
    meas, init, result = tmp_path / "m.nc", tmp_path / "init.nc", tmp_path / "r.nc"
    assert main(["synth", "-o", str(meas), "--photons", "300000"]) == 0
    assert "running on" not in capsys.readouterr().err  # the CPU, as usual: no word
    assert xr.load_dataset(meas).attrs["backend"] == "cpu"
    assert main(["carve", str(meas), "-o", str(init), "--fit-photons", "5000"]) == 0
    assert xr.load_dataset(init).attrs["carving_backend"] == "cpu"
    assert main(["retrieve", str(meas), "--init", str(init), "-o", str(result),
                 "--iterations", "1", "--photons", "2000", "--backend", "cpu"]) == 0
    attrs = xr.load_dataset(result).attrs
    assert attrs["backend"] == "cpu" and attrs["device"].startswith("the CPU (")
    assert main(["report", str(result), "--measurements", str(meas), "-o",
                 str(tmp_path / "report")]) == 0
    summary = (tmp_path / "report" / "summary.md").read_text()
    assert "on the CPU (" in summary and "photons on the cpu back end" in summary


@pytest.mark.skipif(NO_GPU is None, reason="a GPU is here")
def test_asking_for_a_gpu_where_there_is_none_is_a_one_line_error(tmp_path, capsys):
    assert main(["synth", "-o", str(tmp_path / "m.nc"), "--photons", "1000",
                 "--backend", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err == f"cloudct synth: error: backend='cuda': {NO_GPU}\n"
    assert not (tmp_path / "m.nc").exists()


def test_the_demo_settings_follow_the_device(capsys):
    assert main(["demo", "--write-config"]) == 0
    text = capsys.readouterr().out
    assert 'photons = "auto"' in text and "iteration_seconds = 5.0" in text
    assert main(["demo", "--scene", "cloud-field", "--write-config"]) == 0
    assert 'photons = "auto"' in capsys.readouterr().out
    with pytest.raises(SystemExit):  # --photons takes a count or auto
        main(["retrieve", "m.nc", "--photons", "many"])
    assert "--photons: invalid photon_count value: 'many'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="photons must be a count >= 1 or 'auto'"):
        RetrievalConfig(photons="fast")


def test_info_names_the_versions_the_back_ends_and_the_cache(capsys):
    import numba

    from cloudct import __version__
    from cloudct.jit_cache import kernel_cache_dir

    assert main(["info"]) == 0
    out = dict(re.split(r"\s{2,}", line, maxsplit=1)
               for line in capsys.readouterr().out.splitlines())
    assert out["cloudct"] == __version__ and out["numba"] == numba.__version__
    assert out["cuda back end"].startswith("the GPU" if NO_GPU is None else "unavailable")
    if NO_GPU is not None:
        assert NO_GPU in out["cuda back end"]
    assert out["backend 'auto' runs on"] == ("cuda" if NO_GPU is None else "cpu")
    assert str(kernel_cache_dir()) in out["kernel cache"]
