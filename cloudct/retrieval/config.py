"""The settings of a retrieval run (:class:`RetrievalConfig`) and their TOML file.

A configuration file (``cloudct retrieve --config run.toml``; ``cloudct retrieve
--write-config`` prints the defaults, every setting with a comment) holds the run-wide
settings as plain keys and the coarse-to-fine stages as rows of a table, coarse to fine::

    iterations = 300
    photons = 100000
    optimizer = "adam"

    [[stage]]
    pixel_block = 4
    photons = 0.5
    voxel_block = 2

    [[stage]]
    pixel_block = 2
    photons = 1.0
    voxel_block = 1

A key left out takes its default; a stage key is given in every row or in none. Unknown
keys, wrong types and values are refused with one line naming the file and the key. The
resolved configuration is stored with every result and checkpoint (attribute
``config_toml``), and that text re-runs the same retrieval (docs/retrieval_config.md).
"""

from __future__ import annotations

import difflib
import json
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

from cloudct.mc.gradient import ESTIMATORS
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - the backport (pyproject: tomli where Python < 3.11)
    import tomli as tomllib

RECYCLING = ("none", "fixed", "adaptive")
OPTIMIZERS = ("adam", "sgd", "lbfgsb")
# per-stage settings that may be given as None: (field, type, value at every stage with Adam
# or SGD, with L-BFGS-B); the first-order values are those of the best measured run on the
# single cloud (docs/benchmarks.md)
PER_STAGE_DEFAULTS = (
    ("stage_photons", float, 1.0, 1.0), ("voxel_blocks", int, 1, 1),
    ("stage_steps", float, 1.0, 1.0),
    ("gradient_smoothing", float, 1.0, 0.0), ("image_photons", float, 4.0, 1.0),
)
AVERAGING = ("none", "uniform", "ema")
#: The transmittance a retrieval assumes: exponential or the measurements' model.
TRANSMITTANCE = ("exponential", "medium")


@dataclass
class RetrievalConfig:
    """Settings of a retrieval run (all stored in checkpoints and results).

    The defaults are those of the best measured run on the seed paper's single cloud from
    the soft-carved start (docs/benchmarks.md): one stage at 2 x 2 pixel blocks, the
    gradient smoothed over 1 voxel, 4x photons for the residual's images, Adam with a step
    of 1 /km halved whenever the loss saturates, and the gradient by sample matching from
    pixels drawn in proportion to |residual| (``estimator``, ``pixel_sampling``: 100-400
    times the score function's precision per second near the plateau, docs/benchmarks.md;
    the score function where stored paths are replayed, which only it can). The seed
    paper's step of 2 /km with
    coarse-to-fine stages 4, 2, 1 walks away from that start. The L1 prior (``sparsity``,
    :meth:`Retrieval.l1_gradient`) is off by default: it changes what is estimated, and its
    weight was measured on that cloud (0.01 /km^2 lowered epsilon there) and checked on one
    more (benchmarks/scenes.py two_cumuli: the same gain).

    ``transmittance="medium"`` retrieves under the measurements' (non-exponential) model,
    differentiated by the score function alone (its default estimator there; recycling and
    L-BFGS-B refused); ``"exponential"`` assumes exp(-tau) (docs/transmittance.md).

    ``optimizer="lbfgsb"`` makes every iteration a window of L-BFGS-B on the sample-average
    loss of fixed paths (:mod:`cloudct.retrieval.sample_average`): up to ``period``
    evaluations within a trust region of ``trust_region`` (x the stage's step multiple and
    the step decay) relative to each voxel's extinction; ``step`` does not apply, and the
    gradient preconditioners (voxel blocks, smoothing) and the recycling policies are
    refused.
    """

    iterations: int = 300
    photons: int = 100_000  # gradient's per iteration at the finest stage (see image_photons)
    optimizer: str = "adam"  # "adam", "sgd" or "lbfgsb"
    step: float = 1.0  # 1/km per iteration for Adam
    seed: int = 0
    stages: tuple[int, ...] = (2,)  # pixel block sizes, coarse to fine
    stage_photons: tuple[float, ...] | None = None  # per stage: photon fraction (None: 1)
    voxel_blocks: tuple[int, ...] | None = None  # per stage: voxels tied in blocks (None: 1)
    stage_steps: tuple[float, ...] | None = None  # per stage: step as a multiple of `step`
    gradient_smoothing: tuple[float, ...] | None = None  # per stage: Gaussian sigma, voxels
    # (None: 1; 0 with lbfgsb)
    image_photons: tuple[float, ...] | None = None  # per stage: residual images' photons as a
    # multiple of the gradient's (None: 4; 1 with lbfgsb)
    saturation_window: int = 10  # iterations over which the loss must keep decreasing
    saturation_tolerance: float = 0.02  # relative decrease below which the loss saturates
    step_decay: float = 0.5  # last stage: step x this whenever the loss saturates (1: never)
    checkpoint_every: int = 20
    time_limit: float | None = None  # seconds; stop after this much wall time
    recycling: str = "none"  # "none", "fixed" (every `period` iterations) or "adaptive" (ESS)
    period: int = 30  # fixed period N_r, the adaptive policy's maximum period, or lbfgsb's
    # evaluations per window
    min_ess: float = 0.5  # adaptive: resample when ESS / paths falls below this
    recycling_memory: float | None = None  # GiB for the two path stores of the recycling
    # or of an lbfgsb window (None: camera connections while a store fits 2 GiB)
    recycle_gradient: bool = True  # False: recycle only the residual's images and trace the
    # gradient's paths fresh every iteration (Retrieval._recycled_loss_and_gradient)
    trust_region: float = 0.3  # lbfgsb: relative change of a voxel's extinction per window
    sparsity: float = 0.0  # 1/km^2: weight of the L1 prior (Retrieval.l1_gradient)
    estimator: tuple[str, ...] | None = None  # per stage: gradient estimator, one of
    # cloudct.mc.gradient.ESTIMATORS (None: "sm", or "score" where the gradient is replayed)
    pixel_sampling: str | None = None  # camera-side estimators: pixels "uniform" or
    # drawn in proportion to |residual| (cloudct.mc.pixel_sampling; None: "residual")
    averaging: str = "none"  # iterate average (Retrieval.average): "none", "uniform"
    # (Polyak-Ruppert) or "ema" (exponential moving average), restarted at every stage
    # change and step decay
    averaging_decay: float = 0.9  # "ema": weight of the average so far at each iterate
    transmittance: str = "exponential"  # or "medium": the measurements' transmittance model
    # and mode field (differentiated by the score function only)

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        self.stages = tuple(int(s) for s in self.stages)
        quasi_newton = self.optimizer == "lbfgsb"
        for name, kind, first_order, lbfgsb in PER_STAGE_DEFAULTS:  # None: the default
            default = lbfgsb if quasi_newton else first_order
            values = getattr(self, name)
            values = (default,) * len(self.stages) if values is None else values
            setattr(self, name, tuple(kind(v) for v in values))
        if self.transmittance not in TRANSMITTANCE:
            raise ValueError(f"transmittance must be one of {TRANSMITTANCE}, got "
                             f"{self.transmittance!r}")
        model = self.transmittance == "medium"
        if self.estimator is None:  # the best measured, where stored paths are not replayed
            replayed = quasi_newton or (self.recycling != "none" and self.recycle_gradient)
            self.estimator = ("score" if replayed or model else "sm",) * len(self.stages)
        self.estimator = tuple(str(name) for name in self.estimator)
        camera_side = any(name != "score" for name in self.estimator)
        if self.pixel_sampling is None:
            self.pixel_sampling = "residual" if camera_side else "uniform"
        per_stage = (self.stage_photons, self.voxel_blocks, self.stage_steps,
                     self.gradient_smoothing, self.image_photons, self.estimator)
        if not self.stages or any(len(v) != len(self.stages) for v in per_stage):
            raise ValueError(
                "stages, stage_photons, voxel_blocks, stage_steps, gradient_smoothing, "
                "image_photons and estimator must have the same, non-zero length"
            )
        if any(name not in ESTIMATORS for name in self.estimator):
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator}")
        if self.pixel_sampling not in PIXEL_SAMPLINGS:
            raise ValueError(
                f"pixel_sampling must be one of {PIXEL_SAMPLINGS}, got {self.pixel_sampling!r}"
            )
        if self.pixel_sampling != "uniform" and not camera_side:
            raise ValueError("pixel_sampling applies to the camera-side estimators (drt, sm); "
                             "every stage uses the score function")
        if camera_side and (quasi_newton or (self.recycling != "none"
                                             and self.recycle_gradient)):
            raise ValueError(
                "recycled gradients (a recycling policy without recycle_gradient=False) and "
                "optimizer 'lbfgsb' replay stored forward paths: they need the estimator "
                "'score' at every stage"
            )
        if model and (camera_side or quasi_newton or self.recycling != "none"):
            raise ValueError(
                "transmittance 'medium' (a non-exponential model) is differentiated by the "
                "path score function alone, without stored paths: use the estimator 'score' "
                "at every stage, recycling 'none' and the optimizer adam or sgd"
            )
        if min(self.stages) < 1:
            raise ValueError(f"stages (pixel blocks) must be >= 1, got {self.stages}")
        if min(self.gradient_smoothing) < 0.0:
            raise ValueError(f"gradient_smoothing must be >= 0, got {self.gradient_smoothing}")
        if min(self.stage_steps) <= 0.0:
            raise ValueError(f"stage_steps must be > 0, got {self.stage_steps}")
        if not 0.0 < self.step_decay <= 1.0:
            raise ValueError(f"step_decay must be in (0, 1], got {self.step_decay}")
        if min(self.voxel_blocks) < 1:
            raise ValueError(f"voxel_blocks must be >= 1, got {self.voxel_blocks}")
        if self.iterations < 0 or self.photons < 1 or self.checkpoint_every < 1:
            raise ValueError("iterations >= 0, photons >= 1 and checkpoint_every >= 1 needed")
        if min(self.stage_photons) <= 0.0:
            raise ValueError(f"stage_photons must be > 0, got {self.stage_photons}")
        if min(self.image_photons) <= 0.0:
            raise ValueError(f"image_photons must be > 0, got {self.image_photons}")
        if self.recycling not in RECYCLING:
            raise ValueError(f"recycling must be one of {RECYCLING}, got {self.recycling!r}")
        if not 0.0 < self.trust_region <= 1.0:
            raise ValueError(f"trust_region must be in (0, 1], got {self.trust_region}")
        if not self.recycle_gradient and self.recycling == "none":
            raise ValueError("recycle_gradient=False needs a recycling policy (it recycles "
                             "the residual's images only)")
        if self.recycling_memory is not None and not self.recycling_memory > 0.0:
            raise ValueError(
                f"recycling_memory must be a positive number of GiB, got {self.recycling_memory}"
            )
        if self.sparsity < 0.0:
            raise ValueError(f"sparsity must be >= 0, got {self.sparsity}")
        if self.averaging not in AVERAGING:
            raise ValueError(f"averaging must be one of {AVERAGING}, got {self.averaging!r}")
        if not 0.0 < self.averaging_decay < 1.0:
            raise ValueError(f"averaging_decay must be in (0, 1), got {self.averaging_decay}")
        if quasi_newton and (
            self.recycling != "none" or max(self.voxel_blocks) > 1
            or max(self.gradient_smoothing) > 0.0 or self.sparsity > 0.0
        ):
            raise ValueError(
                "optimizer 'lbfgsb' recycles its own paths (period evaluations per window) "
                "and minimises the sample-average loss alone: leave recycling at 'none', "
                "voxel_blocks at 1, gradient_smoothing at 0 and sparsity at 0"
            )

    def photons_at(self, stage: int) -> tuple[int, int]:
        """Photons of an iteration at ``stage``: (images of the residual, gradient)."""
        gradient = max(int(self.photons * self.stage_photons[stage]), 1)
        return max(int(round(gradient * self.image_photons[stage])), 1), gradient

    def recycling_bytes(self) -> float | None:
        """The path stores' memory budget in bytes (None: the recycler's default)."""
        return None if self.recycling_memory is None else self.recycling_memory * 2**30

    def policy(self):
        """The recycling policy of these settings (None without recycling)."""
        from cloudct.recycling.policy import AdaptiveESS, FixedPeriod

        if self.recycling == "fixed":
            return FixedPeriod(self.period)
        if self.recycling == "adaptive":
            return AdaptiveESS(min_fraction=self.min_ess, max_period=self.period)
        return None


# ----------------------------------------------------------------------------------------
# The TOML file
# ----------------------------------------------------------------------------------------


class Key(NamedTuple):
    """A key of the file: its name, the :class:`RetrievalConfig` field that holds its value
    (for a ``[[stage]]`` key, the stages' values), its type, the one-line comment that
    ``--write-config`` writes, and an example value for a setting left unset."""

    name: str
    field: str
    kind: type
    comment: str
    example: Any = None


def _run_key(name: str, kind: type, comment: str, example: Any = None) -> Key:
    return Key(name, name, kind, comment, example)


#: The run-wide keys, in the order the file lists them (every field but the per-stage ones).
RUN_KEYS = {k.name: k for k in (
    _run_key("iterations", int, "iterations in all (a resumed run may raise it)"),
    _run_key("photons", int, "gradient paths per iteration (x each stage's photons; the "
             "residual's images: x image_photons)"),
    _run_key("optimizer", str, "adam, sgd, or lbfgsb (L-BFGS-B windows on recycled paths)"),
    _run_key("step", float, "step size [1/km per iteration] (adam, sgd)"),
    _run_key("step_decay", float, "last stage: multiply the step by this when the loss "
             "saturates (1: never)"),
    _run_key("saturation_window", int, "iterations over which the loss must keep falling "
             "to stay in a stage"),
    _run_key("saturation_tolerance", float, "relative decrease of the loss over a window "
             "below which it saturates"),
    _run_key("sparsity", float, "weight of an L1 prior on the cloud extinction [1/km^2] "
             "(0: none)"),
    _run_key("pixel_sampling", str, "drt, sm: pixels drawn uniformly or in proportion to "
             "|residual| (unset: residual; uniform with score)", "residual"),
    _run_key("recycling", str, "path recycling: none, fixed (every period iterations) or "
             "adaptive (when the ESS falls)"),
    _run_key("period", int, "recycling period (fixed) or maximum period (adaptive); "
             "lbfgsb: evaluations per window"),
    _run_key("min_ess", float, "adaptive recycling: resample when the ESS fraction falls "
             "below this"),
    _run_key("recycle_gradient", bool, "false: recycle only the residual's images, trace "
             "the gradient's paths fresh every iteration"),
    _run_key("recycling_memory", float, "GiB for the two path stores (unset: camera "
             "connections while a store fits 2 GiB)", 2.0),
    _run_key("trust_region", float, "lbfgsb: relative change of a voxel's extinction per "
             "window"),
    _run_key("averaging", str, "iterate average: none, uniform (Polyak-Ruppert) or ema; "
             "restarted at stage changes and step decays"),
    _run_key("averaging_decay", float, "ema averaging: weight of the average so far at each "
             "iterate"),
    _run_key("transmittance", str, "exponential, or medium: the measurements' transmittance "
             "model and mode field (estimator score, no recycling)"),
    _run_key("seed", int, "seed of the photons: the same seed repeats the same iterates"),
    _run_key("checkpoint_every", int, "iterations between checkpoints"),
    _run_key("time_limit", float, "seconds of wall time after which the run stops (unset: "
             "no limit)", 3600.0),
)}

#: The keys of a ``[[stage]]`` row, in the order the file lists them.
STAGE_KEYS = {k.name: k for k in (
    Key("pixel_block", "stages", int, "images averaged over blocks of this many x this "
        "many pixels"),
    Key("photons", "stage_photons", float, "gradient paths as a multiple of photons"),
    Key("image_photons", "image_photons", float, "the residual's images' photons as a "
        "multiple of the gradient's (unset: 4; 1 with lbfgsb)"),
    Key("step", "stage_steps", float, "the step as a multiple of step"),
    Key("voxel_block", "voxel_blocks", int, "voxels tied in blocks of this size"),
    Key("smoothing", "gradient_smoothing", float, "Gaussian sigma [voxels] of the "
        "gradient's smoothing inside the hull (unset: 1; 0 with lbfgsb)"),
    Key("estimator", "estimator", str, "gradient estimator: score, drt or sm (unset: sm; "
        "score where stored paths are replayed or the transmittance is the medium's)"),
)}
#: RetrievalConfig's per-stage field -> the ``[[stage]]`` key.
STAGE_FIELDS = {k.field: name for name, k in STAGE_KEYS.items()}
#: Settings whose default depends on others (the optimiser, the recycling, the estimator).
DEPENDENT = ("gradient_smoothing", "image_photons", "estimator", "pixel_sampling")
_KINDS = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}


class ConfigFileError(ValueError):
    """A configuration file that is not TOML, or holds unknown keys or wrong values."""


def toml_value(value: Any) -> str:
    """``value`` as TOML (numbers with every digit: floats round-trip exactly)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "a table"
    return repr(value)


def config_to_toml(config: RetrievalConfig, *, comments: bool = False,
                   header: str | None = None, unset: tuple[str, ...] = ()) -> str:
    """The TOML text of ``config``: run-wide keys, then one ``[[stage]]`` row per stage.
    With ``comments`` every key has a one-line comment above it. A setting that is None
    (no time limit, ...) and the fields of ``unset`` (settings left to their defaults,
    which may depend on others: the optimiser's, the estimator's) are written commented
    out with ``comments`` and left out without."""
    lines = [] if header is None else [*(f"# {line}" for line in header.splitlines()), ""]

    def add(name: str, key: Key, value: Any, commented: bool, comment: bool) -> None:
        if comments and comment:
            lines.append(f"# {key.comment}")
        if value is None:
            value = key.example
        if not commented:
            lines.append(f"{name} = {toml_value(value)}")
        elif comments:
            lines.append(f"# {name} = {toml_value(value)}")

    for name, key in RUN_KEYS.items():
        value = getattr(config, name)
        add(name, key, value, value is None or name in unset, True)
    for stage in range(len(config.stages)):
        lines.append("")
        if comments and stage == 0:
            lines.append("# the coarse-to-fine stages, coarse to fine: one [[stage]] row each")
        lines.append("[[stage]]")
        for name, key in STAGE_KEYS.items():
            add(name, key, getattr(config, key.field)[stage], key.field in unset,
                stage == 0)
    return "\n".join(lines) + "\n"


def _typed(value: Any, key: Key, where: str) -> Any:
    """``value`` of ``key`` checked against its type (an integer where a number is wanted
    becomes a float); ``where`` starts the message."""
    ok = isinstance(value, key.kind) and not (key.kind is not bool and isinstance(value, bool))
    if key.kind is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        raise ConfigFileError(f"{where}{key.name} must be {_KINDS[key.kind]}, got "
                              f"{toml_value(value)}")
    return value


def _unknown(name: str, where: str, in_stage: bool) -> ConfigFileError:
    """The error of an unknown key, with a hint: the key meant, or where it belongs."""
    if in_stage and name in RUN_KEYS:
        hint = (f"; {name} is a run-wide key: write it above the first [[stage]] (a key "
                "below a [[stage]] header belongs to that row)")
    elif not in_stage and (name == "stages" or name in STAGE_FIELDS):
        hint = "; the per-stage settings are [[stage]] rows (docs/retrieval_config.md)"
    elif not in_stage and name in STAGE_KEYS:
        hint = f"; {name} belongs in the [[stage]] rows"
    else:
        close = difflib.get_close_matches(name, STAGE_KEYS if in_stage else RUN_KEYS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigFileError(f"{where}unknown key {name!r}{hint}")


def parse_config(text: str, source: str = "configuration") -> dict[str, Any]:
    """The :class:`RetrievalConfig` fields that the TOML ``text`` sets, its keys and types
    checked (values are checked by :func:`config_from_settings`); ``source`` (the file)
    starts every message."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigFileError(f"{source} is not a TOML file: {err}") from None
    settings: dict[str, Any] = {}
    for name, value in data.items():
        if name == "stage":
            settings.update(_parse_stages(value, source))
        elif name in RUN_KEYS:
            settings[name] = _typed(value, RUN_KEYS[name], f"{source}: ")
        else:
            raise _unknown(name, f"{source}: ", in_stage=False)
    return settings


def _parse_stages(rows: Any, source: str) -> dict[str, tuple]:
    if not isinstance(rows, list) or not all(isinstance(row, dict) for row in rows):
        raise ConfigFileError(f"{source}: stage must be [[stage]] tables, one per "
                              f"coarse-to-fine stage, got {toml_value(rows)}")
    if not rows:
        raise ConfigFileError(f"{source}: stage holds no [[stage]] row")
    for i, row in enumerate(rows, 1):
        for name, value in row.items():
            if name not in STAGE_KEYS:
                raise _unknown(name, f"{source}: [[stage]] {i}: ", in_stage=True)
            _typed(value, STAGE_KEYS[name], f"{source}: [[stage]] {i}: ")
    settings = {}
    for name, key in STAGE_KEYS.items():
        given = [i for i, row in enumerate(rows, 1) if name in row]
        if name == "pixel_block" and len(given) < len(rows):
            missing = next(i for i in range(1, len(rows) + 1) if i not in given)
            raise ConfigFileError(f"{source}: [[stage]] {missing} lacks pixel_block (its "
                                  "pixel block size)")
        if given and len(given) < len(rows):
            missing = next(i for i in range(1, len(rows) + 1) if i not in given)
            raise ConfigFileError(
                f"{source}: [[stage]] {missing} lacks {name}, which [[stage]] {given[0]} "
                f"gives: give {name} in every [[stage]] row or in none (none: its default)"
            )
        if given:
            settings[key.field] = tuple(_typed(row[name], key, "") for row in rows)
    return settings


def config_from_settings(settings: dict[str, Any], source: str | None = None
                         ) -> RetrievalConfig:
    """``RetrievalConfig(**settings)``; with ``source`` (a file) its messages name the file
    and the keys as the file writes them."""
    try:
        return RetrievalConfig(**settings)
    except ValueError as err:
        if source is None:
            raise
        message = str(err)
        for field, name in STAGE_FIELDS.items():
            message = re.sub(rf"\b{field}\b", f"[[stage]] {name}", message)
        raise ConfigFileError(f"{source}: {message}") from None


def read_config_text(path: str | Path) -> str:
    """The TOML text of a configuration file, or the configuration stored in a cloudct
    result or checkpoint netCDF file (``cloudct retrieve --config result.nc``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"configuration file {path} does not exist")
    raw = path.read_bytes()
    if raw[:4] == b"\x89HDF" or raw[:3] == b"CDF":
        from cloudct.netcdf import load_netcdf

        attrs = load_netcdf(path, "result").attrs
        if "config_toml" in attrs:
            return str(attrs["config_toml"])
        if "config" in attrs:
            return config_to_toml(config_from_json(attrs["config"]))
        raise ConfigFileError(f"{path} holds no retrieval configuration (attribute "
                              "config_toml); is it a cloudct result or checkpoint?")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigFileError(f"{path} is not a TOML file: it is not UTF-8 text") from None


def load_config(path: str | Path, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """The settings of a configuration file (:func:`parse_config`), checked by building
    the configuration they give on top of ``base`` (settings; None: the defaults)."""
    settings = parse_config(read_config_text(path), str(path))
    config_from_settings({**(base or {}), **settings}, str(path))
    return settings


def config_from_json(text: str) -> RetrievalConfig:
    """The configuration of a result's or checkpoint's ``config`` attribute (JSON)."""
    settings = json.loads(text)
    # checkpoints from before the estimator choice traced the score function
    settings.setdefault("estimator", ("score",) * len(settings["stages"]))
    settings.setdefault("pixel_sampling", "uniform")
    return RetrievalConfig(**settings)


#: Settings that a resumed run may change.
RESUMABLE = ("iterations", "time_limit")


def _normalised(name: str, value: Any) -> Any:
    """``value`` of field ``name`` as RetrievalConfig holds it (tuples of the field's type)."""
    kinds = {name: kind for name, kind, *_ in PER_STAGE_DEFAULTS} | {"stages": int,
                                                                     "estimator": str}
    if name in kinds:
        return tuple(kinds[name](v) for v in value)
    if name in RUN_KEYS and value is not None:
        return RUN_KEYS[name].kind(value)
    return value


class ResumeConflict(ValueError):
    """Settings asked of a resumed run that differ from its checkpoint's; ``conflicts``:
    field -> (asked, the checkpoint's)."""

    def __init__(self, conflicts: dict[str, tuple[Any, Any]]) -> None:
        self.conflicts = conflicts
        super().__init__(resume_message(
            {f"{name} = {toml_value(asked)}": toml_value(kept)
             for name, (asked, kept) in conflicts.items()}
        ))


def resume_message(conflicts: dict[str, str]) -> str:
    """One line: each asked setting (as the caller wrote it) and the checkpoint's value."""
    parts = [f"{asked} differs from the checkpoint's {kept}" for asked, kept in conflicts.items()]
    return "; ".join(parts) + "; resume with the checkpoint's settings or start a new run"


def check_resume(checkpoint: RetrievalConfig, asked: dict[str, Any]) -> RetrievalConfig:
    """The checkpoint's configuration with the settings of ``asked`` that a resumed run may
    change (:data:`RESUMABLE`); raises :class:`ResumeConflict` for the others that differ
    from the checkpoint's."""
    conflicts = {
        name: (value, getattr(checkpoint, name)) for name, value in asked.items()
        if name not in RESUMABLE and _normalised(name, value) != getattr(checkpoint, name)
    }
    if conflicts:
        raise ResumeConflict(conflicts)
    changed = {name: asked[name] for name in RESUMABLE if name in asked}
    return RetrievalConfig(**{**asdict(checkpoint), **changed}) if changed else checkpoint
