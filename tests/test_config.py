"""The retrieval's configuration file (``cloudct retrieve --config``, ``--write-config``):
file and command line give the same settings, the command line overrides the file, bad
files end in one line, the stored configuration re-runs the same retrieval, and a resumed
run refuses settings that differ from its checkpoint's."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from test_retrieval import initial_guess
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.cli import build_parser, main
from cloudct.cli.retrieve import DEMO_CONFIG
from cloudct.cli.run_options import config_from_options
from cloudct.mc.render import render
from cloudct.measurements import load_measurements, save_measurements
from cloudct.medium import load_medium, save_medium
from cloudct.retrieval.config import settings_for_optics
from cloudct.retrieval.config_file import (
    RUN_KEYS,
    STAGE_FIELDS,
    ResumeConflict,
    config_to_toml,
    load_config,
    parse_config,
)
from cloudct.retrieval.loop import Retrieval, RetrievalConfig
from cloudct.retrieval.priors import Prior
from cloudct.retrieval.report import write_report

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

RUN_TOML = """\
iterations = 7
photons = 3000  # an integer
optimizer = "sgd"
step = 2  # an integer where a number is wanted
seed = 4
sparsity = 0.05
step_decay = 0.25
time_limit = 90.5
checkpoint_every = 3

[[stage]]
pixel_block = 2
photons = 0.5
voxel_block = 2
step = 1.0
smoothing = 1.5
image_photons = 3
estimator = "drt"

[[stage]]
pixel_block = 1
photons = 1.0
voxel_block = 1
step = 0.25
smoothing = 0.0
image_photons = 1.0
estimator = "sm"
"""
RUN_ARGV = ["--iterations", "7", "--photons", "3000", "--optimizer", "sgd", "--step", "2",
            "--seed", "4", "--sparsity", "0.05", "--step-decay", "0.25", "--time-limit",
            "90.5", "--checkpoint-every", "3", "--stages", "2", "1", "--stage-photons", "0.5",
            "1", "--voxel-blocks", "2", "1", "--stage-steps", "1", "0.25",
            "--gradient-smoothing", "1.5", "0", "--image-photons", "3", "1", "--estimator",
            "drt", "sm"]


def settings_of(*argv: str) -> RetrievalConfig:
    """The configuration ``cloudct ARGV`` would run (without running it)."""
    return config_from_options(build_parser().parse_args(list(argv)))


@pytest.fixture
def run_toml(tmp_path) -> Path:
    path = tmp_path / "run.toml"
    path.write_text(RUN_TOML)
    return path


def test_every_setting_has_a_key_of_the_file():
    fields = {f.name for f in dataclasses.fields(RetrievalConfig)}
    assert set(RUN_KEYS) | set(STAGE_FIELDS) | {"priors"} == fields  # [[prior]] rows
    assert not set(RUN_KEYS) & set(STAGE_FIELDS)


def test_a_file_and_the_equivalent_command_line_give_the_same_config(run_toml):
    from_file = settings_of("retrieve", "m.nc", "--config", str(run_toml))
    from_options = settings_of("retrieve", "m.nc", *RUN_ARGV)
    assert from_file == from_options
    assert from_file.stages == (2, 1) and from_file.stage_steps == (1.0, 0.25)
    assert from_file.estimator == ("drt", "sm") and from_file.step == 2.0
    assert settings_of("retrieve", "m.nc") == RetrievalConfig()  # nothing given: defaults


def test_command_line_options_override_the_file(run_toml):
    config = settings_of("retrieve", "m.nc", "--config", str(run_toml), "--photons", "5000",
                         "--stage-photons", "0.25", "1", "--seed", "9")
    expected = dataclasses.replace(settings_of("retrieve", "m.nc", "--config", str(run_toml)),
                                   photons=5000, stage_photons=(0.25, 1.0), seed=9)
    assert config == expected
    # new stages with all their per-stage settings replace the file's rows
    three = ["--stages", "4", "2", "1", "--stage-photons", "1", "1", "1", "--voxel-blocks",
             "1", "1", "1", "--stage-steps", "1", "1", "1", "--gradient-smoothing", "1", "1",
             "1", "--image-photons", "4", "4", "4", "--estimator", "sm", "sm", "sm"]
    assert settings_of("retrieve", "m.nc", "--config", str(run_toml), *three).stages == (4, 2, 1)
    with pytest.raises(ValueError, match=r"--stages gives 3 stages and .*run.toml 2 \[\[stage\]\] "
                       r"rows: give --stage-photons, .*--estimator too"):
        settings_of("retrieve", "m.nc", "--config", str(run_toml), *three[:4])


def test_write_config_prints_the_defaults_as_a_commented_file(capsys, tmp_path):
    assert main(["retrieve", "--write-config"]) == 0  # no measurement file needed
    text = capsys.readouterr().out
    assert load_config_text(text, tmp_path) == RetrievalConfig()
    lines = text.splitlines()
    for name in RUN_KEYS:  # every setting, each with a one-line comment above it
        at = next(i for i, line in enumerate(lines)
                  if line.lstrip("# ").startswith(f"{name} = "))
        assert lines[at - 1].startswith("# ") and " = " not in lines[at - 1], name
    assert "[[stage]]" in lines and "pixel_block = 2" in lines
    # the settings whose defaults follow the optimiser are left commented: switching to
    # L-BFGS-B in the file gives L-BFGS-B's own defaults
    assert "# smoothing = 1.0" in lines and "# estimator = \"sm\"" in lines
    lbfgsb = text.replace('optimizer = "adam"', 'optimizer = "lbfgsb"')
    assert load_config_text(lbfgsb, tmp_path) == RetrievalConfig(optimizer="lbfgsb")
    # the demo's: its bundled file
    assert main(["demo", "--write-config"]) == 0
    demo = RetrievalConfig(iterations=120)
    assert load_config_text(capsys.readouterr().out, tmp_path) == demo
    assert RetrievalConfig(**load_config(DEMO_CONFIG)) == demo
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "data/*.toml" in pyproject["tool"]["setuptools"]["package-data"]["cloudct"]
    # the options given are written too
    assert main(["retrieve", "--write-config", "--stages", "4", "2", "--photons", "7"]) == 0
    assert load_config_text(capsys.readouterr().out, tmp_path) == RetrievalConfig(
        stages=(4, 2), photons=7)


def load_config_text(text: str, tmp_path: Path) -> RetrievalConfig:
    path = tmp_path / "written.toml"
    path.write_text(text)
    return RetrievalConfig(**load_config(path))


def test_prior_rows_and_the_command_line_give_the_same_terms(tmp_path, capsys):
    text = ('[[prior]]\nterm = "monotonic"\nweight = 0.3\n\n[[prior]]\nterm = "smoothness"'
            '\nweight = 0.1\nschedule = "fixed"\nvertical = 0.5\n')
    path = tmp_path / "run.toml"
    path.write_text(text)
    terms = (Prior("monotonic", 0.3), Prior("smoothness", 0.1, "fixed", {"vertical": 0.5}))
    assert settings_of("retrieve", "m.nc", "--config", str(path)).priors == terms
    argv = ["retrieve", "m.nc", "--prior", "monotonic=0.3",
            "smoothness=0.1,schedule=fixed,vertical=0.5"]
    assert settings_of(*argv).priors == terms
    assert settings_of("retrieve", "m.nc", "--prior", "none").priors == ()
    path.write_text("prior = []\n")
    assert settings_of("retrieve", "m.nc", "--config", str(path)).priors == ()
    # the settings of the runs before the terms: the L1 term alone, from a file or options
    legacy = (Prior("l1", 0.005, "fixed"),)
    path.write_text('sparsity = 0.005\nsparsity_schedule = "fixed"\n')
    assert settings_of("retrieve", "m.nc", "--config", str(path)).priors == legacy
    assert settings_of("retrieve", "m.nc", "--sparsity", "0.005", "--sparsity-schedule",
                       "fixed").priors == legacy
    assert settings_of("retrieve", "m.nc", "--sparsity", "0").priors == ()
    assert main(["retrieve", "m.nc", "--prior", "l1=1", "--sparsity", "0.1"]) == 2
    assert "--sparsity and --sparsity-schedule give the L1 term alone" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit):
        settings_of("retrieve", "m.nc", "--prior", "tv=1")
    assert "prior term must be one of" in capsys.readouterr().err


def test_a_configuration_round_trips_through_its_text():
    configs = [
        RetrievalConfig(),
        RetrievalConfig(optimizer="lbfgsb", stages=(4, 2, 1), trust_region=0.1 + 0.2,
                        recycling_memory=1e-6, time_limit=1.0 / 3.0),
        RetrievalConfig(recycling="adaptive", recycle_gradient=False, estimator=("drt",),
                        pixel_sampling="uniform", averaging="ema", averaging_decay=0.95),
        RetrievalConfig(priors=(Prior("monotonic", 0.25, "fixed"),
                                Prior("smoothness", 1.0 / 3.0, options={"vertical": 0.5}))),
        RetrievalConfig(priors=()),
    ]
    for config in configs:
        for comments in (False, True):
            text = config_to_toml(config, comments=comments, header="a header\non two lines")
            assert RetrievalConfig(**parse_config(text)) == config


BAD_FILES = {
    "unknown key": ("photon = 5\n", "run.toml: unknown key 'photon' (did you mean 'photons'?)"),
    "wrong type": ('photons = "many"\n',
                   'run.toml: photons must be an integer or "auto", got "many"'),
    "float for an integer": ("iterations = 2.5\n",
                             "run.toml: iterations must be an integer, got 2.5"),
    "bad value": ('optimizer = "newton"\n', "run.toml: optimizer must be one of"),
    "parallel lists": ("stages = [4, 2]\n", "run.toml: unknown key 'stages'; the per-stage "
                       "settings are [[stage]] rows"),
    "stage key at the top": ("voxel_block = 2\n", "run.toml: unknown key 'voxel_block'; "
                             "voxel_block belongs in the [[stage]] rows"),
    "unknown stage key": ("[[stage]]\npixel_block = 2\nsmooth = 1.0\n",
                          "run.toml: [[stage]] 1: unknown key 'smooth' (did you mean "
                          "'smoothing'?)"),
    "run-wide key in a row": ("[[stage]]\npixel_block = 2\nstep_decay = 0.5\n",
                              "run.toml: [[stage]] 1: unknown key 'step_decay'; step_decay is "
                              "a run-wide key: write it above the first [[stage]]"),
    "wrong stage type": ('[[stage]]\npixel_block = "2"\n',
                         'run.toml: [[stage]] 1: pixel_block must be an integer, got "2"'),
    "bad stage value": ("[[stage]]\npixel_block = 2\nstep = 0.0\n",
                        "run.toml: [[stage]] step must be > 0, got (0.0,)"),
    "rows of different keys": ("[[stage]]\npixel_block = 4\nphotons = 0.5\n\n"
                               "[[stage]]\npixel_block = 2\n",
                               "run.toml: [[stage]] 2 lacks photons, which [[stage]] 1 gives"),
    "a row without its pixel block": ("[[stage]]\npixel_block = 4\n\n[[stage]]\nstep = 2.0\n",
                                      "run.toml: [[stage]] 2 lacks pixel_block"),
    "stage not a table": ("stage = 2\n", "run.toml: stage must be [[stage]] tables"),
    "unknown prior": ('[[prior]]\nterm = "tv"\nweight = 1.0\n',
                      "run.toml: [[prior]] 1: prior term must be one of"),
    "prior without weight": ('[[prior]]\nterm = "l1"\n',
                             "run.toml: [[prior]] 1: lacks weight"),
    "prior option of another term": ('[[prior]]\nterm = "l1"\nweight = 1.0\nhuber = 2.0\n',
                                     "run.toml: [[prior]] 1: prior l1: unknown option 'huber'"),
    "prior option not a number": ('[[prior]]\nterm = "smoothness"\nweight = 1.0\n'
                                  'vertical = "high"\n', 'run.toml: [[prior]] 1: vertical '
                                  'must be a number, got "high"'),
    "a term twice": ('[[prior]]\nterm = "l1"\nweight = 1.0\n[[prior]]\nterm = "l1"\n'
                     'weight = 2.0\n', "run.toml: priors name a term twice"),
    "the old key and rows": ('sparsity = 0.01\n[[prior]]\nterm = "l1"\nweight = 1.0\n',
                             "run.toml: sparsity (the L1 term's settings before [[prior]] "
                             "rows) and [[prior]] rows: give the rows alone"),
    "not TOML": ("photons = = 3\n", "run.toml is not a TOML file: Invalid value"),
    "not text": (b"\xff\xfe\x00binary", "run.toml is not a TOML file: it is not UTF-8 text"),
}


@pytest.mark.parametrize("content, message", BAD_FILES.values(), ids=BAD_FILES.keys())
def test_a_bad_file_ends_in_one_line_naming_the_file_and_the_key(tmp_path, capsys, content,
                                                                 message):
    path = tmp_path / "run.toml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    assert main(["retrieve", str(tmp_path / "none.nc"), "--config", str(path),
                 "-o", str(tmp_path / "r.nc")]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.replace(str(tmp_path) + "/", "")
    assert err.startswith("cloudct retrieve: error: ") and err.count("\n") == 1, err
    assert message in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "r.nc").exists()


def test_a_missing_file_or_measurement_ends_in_one_line(tmp_path, capsys):
    assert main(["retrieve", "m.nc", "--config", str(tmp_path / "none.toml")]) == 2
    assert "configuration file" in capsys.readouterr().err
    assert main(["retrieve"]) == 2
    assert "the measurement file is missing" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------
# Running: the stored configuration, resuming
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> list[str]:
    """``cloudct retrieve``'s inputs: small measurements and the flat hull."""
    where = tmp_path_factory.mktemp("inputs")
    measured = render(gradient_medium(), gradient_scene(), photons=400_000, seed=77,
                      progress=False)
    save_measurements(measured, where / "meas.nc")
    save_medium(initial_guess(), where / "init.nc")
    return [str(where / "meas.nc"), "--init", str(where / "init.nc")]


SMALL = ["--photons", "1500", "--stages", "2", "1", "--stage-photons", "0.5", "1",
         "--schedule", "threshold", "--saturation-window", "1", "--seed", "5",
         "--sparsity", "0.01"]


def test_the_stored_configuration_reruns_the_same_retrieval(tmp_path, inputs):
    first = tmp_path / "first.nc"
    assert main(["retrieve", *inputs, *SMALL, "--iterations", "2", "-o", str(first)]) == 0
    stored = xr.load_dataset(first)
    text = stored.attrs["config_toml"]
    config = RetrievalConfig(**parse_config(text))
    assert (config.seed, config.stages, config.iterations) == (5, (2, 1), 2)
    (tmp_path / "stored.toml").write_text(text)
    again = tmp_path / "again.nc"
    assert main(["retrieve", *inputs, "--config", str(tmp_path / "stored.toml"),
                 "-o", str(again)]) == 0
    rerun = xr.load_dataset(again)
    for name in ("cloud_extinction", "log_loss", "log_stage"):
        np.testing.assert_array_equal(rerun[name].values, stored[name].values)
    assert rerun.attrs["config_toml"] == text and rerun.attrs["run_id"] == stored.attrs["run_id"]
    # the result file itself is a configuration, and the checkpoint holds it too
    assert settings_of("retrieve", "m.nc", "--config", str(first)) == config
    checkpoint = xr.load_dataset(tmp_path / "first.checkpoint.nc")
    assert checkpoint.attrs["config_toml"] == text
    # the report shows it
    summary = write_report(stored, tmp_path / "report").read_text()
    assert "## Configuration" in summary and f"```toml\n{text}```" in summary


def test_resume_refuses_settings_that_differ_from_the_checkpoints(tmp_path, inputs, capsys):
    out = tmp_path / "r.nc"
    start = ["retrieve", *inputs, *SMALL, "-o", str(out), "--checkpoint-every", "1"]
    assert main([*start, "--iterations", "1"]) == 0
    resume = ["retrieve", *inputs, "-o", str(out), "--resume", "--overwrite", "--backend", "cpu"]
    capsys.readouterr()
    assert main([*resume, "--photons", "2000", "--iterations", "2"]) == 2
    err = capsys.readouterr().err
    assert err == ("cloudct retrieve: error: --photons 2000 differs from the checkpoint's 1500; "
                   "resume with the checkpoint's settings or start a new run\n")
    assert main([*resume, "--stages", "4", "1", "--fresh-gradient"]) == 2
    err = capsys.readouterr().err
    assert "--stages 4 1 differs from the checkpoint's 2 1" in err
    assert "--fresh-gradient differs from the checkpoint's recycle_gradient = true" in err
    config = tmp_path / "other.toml"
    config.write_text("step = 0.25\n[[stage]]\npixel_block = 2\n")
    assert main([*resume, "--config", str(config)]) == 2
    err = capsys.readouterr().err.replace(str(tmp_path) + "/", "")
    assert ("other.toml's step = 0.25 differs from the checkpoint's 0.5; other.toml's "
            "[[stage]] pixel_block values [2] differs from the checkpoint's [2, 1]") in err
    assert xr.load_dataset(out).sizes["iteration"] == 1  # nothing ran
    # the same settings, more iterations and a time limit: it resumes
    assert main([*resume, *SMALL, "--iterations", "3", "--time-limit", "600"]) == 0
    result = xr.load_dataset(out)
    assert result.sizes["iteration"] == 3
    resumed = RetrievalConfig(**parse_config(result.attrs["config_toml"]))
    assert (resumed.iterations, resumed.time_limit, resumed.photons) == (3, 600.0, 1500)
    # the library refuses alike
    with pytest.raises(ResumeConflict, match="photons = 2000 differs from the checkpoint's"):
        Retrieval.resume(tmp_path / "r.checkpoint.nc", xr.load_dataset(inputs[0]),
                         initial_guess(), settings={"photons": 2000})


def test_a_full_peak_mie_medium_is_retrieved_with_the_combined_estimator_unless_told(
        inputs, caplog):
    """With the full Mie peak the combined estimator's gradient is 5.9x as precise per
    second as the score function's and its images have no fireflies (docs/benchmarks.md,
    "Mie optics"): where the settings name no estimator, a Mie medium's retrieval takes it at
    every stage, and its images where they name none, and says so, with path recycling too
    (forward half replayed, backward half fresh); where lbfgsb replays stored paths, the
    score function and forward images, and where the medium's transmittance is
    differentiated, the score function. Settings that name an estimator, a pixel
    sampling or images, and other optics, keep theirs. The command line (given the optics)
    and a Retrieval made without a config follow the same rule."""
    caplog.set_level("INFO", logger="cloudct")
    full = {"phase_truncation": 0.0}  # the full peak
    combined = {"estimator": ("combined",), "image_method": "combined"}
    assert settings_for_optics(full, "mie") == {**full, **combined}
    assert settings_for_optics({**full, "stages": (4, 2, 1)},
                               "mie")["estimator"] == ("combined",) * 3
    for given in ({"estimator": ("drt",)}, {"pixel_sampling": "uniform"}):
        assert settings_for_optics({**full, **given}, "mie") == {
            **full, **given, "image_method": "combined"}
    assert settings_for_optics({**full, "image_method": "forward"}, "mie") == {
        **full, "image_method": "forward", "estimator": ("combined",)}
    assert settings_for_optics({**full, "recycling": "fixed"}, "mie") == {
        **full, "recycling": "fixed", **combined}
    assert settings_for_optics({**full, "optimizer": "lbfgsb"}, "mie") == {
        **full, "optimizer": "lbfgsb", "estimator": ("score",)}
    assert settings_for_optics({**full, "recycling": "fixed", "recycle_gradient": False},
                               "mie")["estimator"] == ("combined",)
    assert settings_for_optics({**full, "transmittance": "medium"},
                               "mie")["estimator"] == ("score",)
    assert settings_for_optics({}, "hg") == {}
    assert "estimator combined: the medium has mie optics" in caplog.text
    assert "image method combined: the medium has mie optics" in caplog.text
    parse = build_parser().parse_args
    no_cut = ["retrieve", "--phase-truncation", "0"]
    config = config_from_options(parse(no_cut), optics="mie")
    assert (config.estimator, config.image_method) == (("combined",), "combined")
    config = config_from_options(parse(["retrieve"]))
    assert (config.estimator, config.image_method) == (("sm",), "forward")
    assert config_from_options(parse([*no_cut, "--estimator", "drt"]),
                               optics="mie").estimator == ("drt",)
    measured, initial = load_measurements(inputs[0]), load_medium(inputs[2])
    assert Retrieval(measured, initial).config.estimator == ("sm",)
    mie = initial.assign_attrs(optics="mie")  # the label the rule reads
    assert Retrieval(measured, mie, RetrievalConfig(**settings_for_optics(
        full, "mie"))).config.estimator == ("combined",)
    with pytest.warns(UserWarning, match="full forward peak and the config names no "
                      "phase_truncation"):  # a config given as it is, but said
        assert Retrieval(measured, mie, RetrievalConfig()).config.estimator == ("sm",)


def test_a_mie_medium_is_retrieved_with_its_peak_cut_unless_told(caplog):
    """Cutting the forward peak at 3 degrees takes a 2-core retrieval of the single cloud's
    Mie measurements to epsilon 0.56 in 15 minutes (0.66-0.69 with the full peak;
    docs/benchmarks.md, "Mie optics"): where the settings name no cut and the medium records
    none, a Mie medium's retrieval cuts it, says so, and keeps the HG defaults (sample
    matching) since its gradient's noise is then HG-like; a cut the medium records, or one
    the settings name, stays; HG media are left alone."""
    caplog.set_level("INFO", logger="cloudct")
    assert settings_for_optics({}, "mie") == {"phase_truncation": 3.0}
    assert "phase truncation 3 degrees: the medium has mie optics" in caplog.text
    assert settings_for_optics({}, "mie", recorded_truncation=2.0) == {}
    assert settings_for_optics({"phase_truncation": 1.5}, "mie") == {"phase_truncation": 1.5}
    assert settings_for_optics({}, "hg") == {}
    parse = build_parser().parse_args
    config = config_from_options(parse(["retrieve"]), optics="mie")
    assert (config.phase_truncation, config.estimator) == (3.0, ("sm",))
