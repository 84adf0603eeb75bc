"""The TOML file of a retrieval run's settings (:class:`~cloudct.retrieval.config.RetrievalConfig`).

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
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

from cloudct.retrieval.config import (
    AUTO,
    LEGACY_SPARSITY,
    PER_STAGE_DEFAULTS,
    RetrievalConfig,
)
from cloudct.retrieval.priors import PRIOR_SCHEDULES, TERMS, Prior, as_prior

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - the backport (pyproject: tomli where Python < 3.11)
    import tomli as tomllib


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
             "images: x image_photons), or \"auto\": fitted to iteration_seconds"),
    _run_key("iteration_seconds", float, "photons \"auto\": the wall time [s] an iteration "
             "aims at (unset: 5 on a CPU, 2 on a GPU)", 5.0),
    _run_key("optimizer", str, "adam, sgd, or lbfgsb (L-BFGS-B windows on recycled paths)"),
    _run_key("step", float, "step size [1/km per iteration] (adam, sgd)"),
    _run_key("schedule", str, "how a plateau of the loss is found: noise (its decrease is "
             "within its noise), threshold (saturation_tolerance) or fixed (no test)"),
    _run_key("saturation_window", int, "iterations of the loss a plateau is judged on"),
    _run_key("significance", float, "schedule noise: the test's false-alarm rate"),
    _run_key("saturation_tolerance", float, "schedule threshold: the relative decrease of "
             "the loss over a window below which it is a plateau"),
    _run_key("plateau", str, "the last stage's answer to a plateau: photons (grow them, then "
             "decay the step) or step"),
    _run_key("photon_growth", float, "plateau photons: the photons x this at a plateau"),
    _run_key("photon_cap", float, "plateau photons: at most this x the count the run "
             "settled at"),
    _run_key("step_decay", float, "multiply the step by this at a plateau of the last stage "
             "(1: never)"),
    _run_key("step_floor", float, "the step never falls below this x its start"),
    _run_key("max_change", float, "per voxel and iteration, |change| <= this x (extinction "
             "+ step) (unset: unbounded)", 0.5),
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
             "model and mode field (estimator score or drt, no recycling)"),
    _run_key("image_method", str, "the residual's images: forward, or combined (forward and "
             "camera paths by multiple importance sampling; recycled: camera paths fresh; not "
             "with lbfgsb)"),
    _run_key("phase_truncation", float, "degrees: Mie phase functions' forward peak cut flat "
             "for the retrieval's paths; 0 keeps it (unset: as the initial medium records; a "
             "Mie medium that records none: 3)", 3.0),
    _run_key("unknowns", tuple, "what is retrieved: [\"extinction\"] (one band), or "
             "[\"lwc\", \"reff\"] (liquid water content and effective radius, several bands)"),
    _run_key("lwc_step", float, "unknowns lwc reff: the step in LWC [g m-3 per iteration]"),
    _run_key("reff_step", float, "unknowns lwc reff: the step in r_eff [micron per "
             "iteration]"),
    _run_key("extinction_share", float, "unknowns lwc reff: the share of the run first "
             "spent retrieving the extinction in the shortest band (0: none)", 0.75),
    _run_key("hold_extinction", bool, "unknowns lwc reff: keep the first guess's extinction "
             "in the shortest band and retrieve r_eff alone (LWC follows it)"),
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
    Key("estimator", "estimator", str, "gradient estimator: score, drt, sm, backward-score "
        "or combined (unset: sm; score where stored paths are replayed or the transmittance "
        "is the medium's; combined for Mie optics with the full peak, except with lbfgsb)"),
)}
#: RetrievalConfig's per-stage field -> the ``[[stage]]`` key.
STAGE_FIELDS = {k.field: name for name, k in STAGE_KEYS.items()}
#: Settings whose default depends on others (the optimiser, the recycling, the estimator).
DEPENDENT = ("gradient_smoothing", "image_photons", "estimator", "pixel_sampling", "priors")
#: The keys of a ``[[prior]]`` row besides the term's options (cloudct.retrieval.priors).
PRIOR_KEYS = ("term", "weight", "schedule")
#: The keys of files written before the prior terms: the L1 term's weight and schedule.
LEGACY_PRIOR_KEYS = ("sparsity", "sparsity_schedule")
_KINDS = {int: "an integer", float: "a number", str: "a string", bool: "true or false",
          tuple: "an array of strings"}
#: Fields whose key also takes the string "auto" (a count chosen by the run).
AUTO_KEYS = ("photons",)


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
    commented = "priors" in unset
    if not config.priors and (comments or not commented):
        lines.append(f"{'# ' if commented else ''}prior = []")
    for stage in range(len(config.stages)):
        lines.append("")
        if comments and stage == 0:
            lines.append("# the coarse-to-fine stages, coarse to fine: one [[stage]] row each")
        lines.append("[[stage]]")
        for name, key in STAGE_KEYS.items():
            add(name, key, getattr(config, key.field)[stage], key.field in unset,
                stage == 0)
    if comments:
        lines += ["", "# the loss's prior terms, one [[prior]] row each (prior = [] above: none;"
                  " unset: the", "# defaults, none with lbfgsb): term (one of "
                  f"{', '.join(TERMS)}), weight, schedule", f"# ({' or '.join(PRIOR_SCHEDULES)})"
                  " and the term's options (docs/retrieval_config.md)"]
    for prior in config.priors:
        if comments or not commented:
            lines.append("")
        row = {"term": prior.term, "weight": prior.weight, "schedule": prior.schedule,
               **prior.options}
        for name, value in (("", "[[prior]]"), *row.items()):
            text = value if not name else f"{name} = {toml_value(value)}"
            if not commented:
                lines.append(text)
            elif comments:
                lines.append(f"# {text}")
    return "\n".join(lines) + "\n"


def _typed(value: Any, key: Key, where: str) -> Any:
    """``value`` of ``key`` checked against its type (an integer where a number is wanted
    becomes a float); ``where`` starts the message."""
    if key.field in AUTO_KEYS and value == AUTO:
        return value
    ok = isinstance(value, key.kind) and not (key.kind is not bool and isinstance(value, bool))
    if key.kind is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if key.kind is tuple and isinstance(value, list) and all(isinstance(v, str) for v in value):
        value, ok = tuple(value), True
    if not ok:
        also = f' or "{AUTO}"' if key.field in AUTO_KEYS else ""
        raise ConfigFileError(f"{where}{key.name} must be {_KINDS[key.kind]}{also}, got "
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
    legacy = {name: data.pop(name) for name in LEGACY_PRIOR_KEYS if name in data}
    if legacy:
        if "prior" in data:
            raise ConfigFileError(f"{source}: {' and '.join(legacy)} (the L1 term's settings "
                                  "before [[prior]] rows) and [[prior]] rows: give the rows "
                                  "alone")
        weight = _typed(legacy.get("sparsity", LEGACY_SPARSITY),
                        Key("sparsity", "priors", float, ""), f"{source}: ")
        schedule = _typed(legacy.get("sparsity_schedule", "noise"),
                          Key("sparsity_schedule", "priors", str, ""), f"{source}: ")
        settings["priors"] = legacy_priors(weight, schedule, source)
    for name, value in data.items():
        if name == "stage":
            settings.update(_parse_stages(value, source))
        elif name == "prior":
            settings["priors"] = _parse_priors(value, source)
        elif name in RUN_KEYS:
            settings[name] = _typed(value, RUN_KEYS[name], f"{source}: ")
        else:
            raise _unknown(name, f"{source}: ", in_stage=False)
    return settings


def legacy_priors(sparsity: float, schedule: str, source: str | None = None
                  ) -> tuple[Prior, ...]:
    """The priors of the settings ``sparsity`` and ``sparsity_schedule`` of files and
    results written before the prior terms (the L1 term alone; none at weight 0)."""
    try:
        return (Prior("l1", sparsity, schedule),) if sparsity > 0.0 else ()
    except ValueError as err:
        if source is None:
            raise
        raise ConfigFileError(f"{source}: {str(err).replace('prior l1: ', 'sparsity ')}"
                              ) from None


def _parse_priors(rows: Any, source: str) -> tuple[Prior, ...]:
    """``[[prior]]`` rows (or ``prior = []``) as :class:`Prior` terms, each checked."""
    if not isinstance(rows, list) or not all(isinstance(row, dict) for row in rows):
        raise ConfigFileError(f"{source}: prior must be [[prior]] tables, one per term, or "
                              f"[] for none, got {toml_value(rows)}")
    priors = []
    for i, row in enumerate(rows, 1):
        where = f"{source}: [[prior]] {i}: "
        missing = [k for k in ("term", "weight") if k not in row]
        if missing:
            raise ConfigFileError(f"{where}lacks {missing[0]} (every row names its term and "
                                  "weight)")
        for name, kind in (("term", str), ("schedule", str), ("weight", float)):
            if name in row:
                row[name] = _typed(row[name], Key(name, "priors", kind, ""), where)
        options = {k: _typed(v, Key(k, "priors", float, ""), where) for k, v in row.items()
                   if k not in PRIOR_KEYS}
        try:
            priors.append(Prior(row["term"], row["weight"], row.get("schedule", "noise"),
                                options))
        except ValueError as err:
            raise ConfigFileError(f"{where}{err}") from None
    return tuple(priors)


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
    # and before the noise test, the step halved at every plateau without a floor
    settings.update({k: v for k, v in (("schedule", "threshold"), ("plateau", "step"),
                                       ("step_floor", 0.0)) if k not in settings})
    # before the prior terms, the L1 term alone (none before it)
    sparsity = settings.pop("sparsity", 0.0)
    schedule = settings.pop("sparsity_schedule", "fixed")
    settings.setdefault("priors", legacy_priors(sparsity or 0.0, schedule))
    return RetrievalConfig(**settings)


#: Settings that a resumed run may change.
RESUMABLE = ("iterations", "time_limit")


def _normalised(name: str, value: Any) -> Any:
    """``value`` of field ``name`` as RetrievalConfig holds it (tuples of the field's type)."""
    kinds = {name: kind for name, kind, *_ in PER_STAGE_DEFAULTS} | {"stages": int,
                                                                     "estimator": str}
    if name in kinds:
        return tuple(kinds[name](v) for v in value)
    if name == "priors":
        return tuple(as_prior(p) for p in value)
    if name in RUN_KEYS and value is not None:
        return value if value == AUTO else RUN_KEYS[name].kind(value)
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
