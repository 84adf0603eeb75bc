"""The chain on the device that is there: every command takes --backend cpu|cuda|auto and
records where it ran, and photons = "auto" fits the photons per iteration to the device."""

from __future__ import annotations

import json
import re

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


def test_auto_photons_skip_the_first_iteration_and_log_every_change(measurements):
    run = Retrieval(measurements, initial_guess(),
                    RetrievalConfig(photons="auto", iteration_seconds=10.0, iterations=0))
    s = run.state
    assert (s.photons, s.photons_settled) == (start_count("cpu"), False)
    run._schedule(300.0)  # the first of the process: compiling, not used
    assert s.photons == start_count("cpu") and not s.decisions
    run._schedule(1.0)
    assert s.photons == 10 * start_count("cpu") and not s.photons_settled
    run._schedule(11.0)
    assert s.photons_settled and s.photons == s.photons_base == 10 * start_count("cpu")
    run._schedule(1.0)  # settled: it stays
    assert s.photons == 10 * start_count("cpu")
    assert [d["what"] for d in s.decisions] == ["photons 50000 -> 500000",
                                                "photons settled at 500000"]
    fixed = Retrieval(measurements, initial_guess(), RetrievalConfig(photons=7000))
    fixed._schedule(1.0)
    fixed._schedule(1.0)
    assert (fixed.state.photons, fixed.state.decisions) == (7000, [])


def test_an_auto_run_traces_the_counts_it_chose_and_resumes_with_them(tmp_path, measurements):
    # a tiny problem's iterations take far less than the target: the count grows
    config = RetrievalConfig(photons="auto", iteration_seconds=1e6, iterations=3,
                             stages=(1,), checkpoint_every=1)
    run = Retrieval(measurements, initial_guess(), config)
    run.state.photons = 1000  # keep the test's iterations short
    result = run.run(checkpoint=tmp_path / "ck.nc", progress=False)
    photons = result["log_photons"].values  # images' (x2) and gradient's photons
    assert list(photons) == [3 * 1000, 3 * 1000, 3 * 16_000]
    decisions = json.loads(result.attrs["decisions"])
    assert [d["iteration"] for d in decisions] == [2, 3]
    assert result.attrs["photons_now"] == 260_000 and result.attrs["photons_settled"] == 0
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess())
    assert (resumed.state.photons, resumed.state.decisions) == (260_000, decisions)
    summary = write_report(result, tmp_path / "report").read_text()
    assert "## What the run changed on its own" in summary
    assert "| 2 | photons 1000 -> 16000 | photons auto:" in summary


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
