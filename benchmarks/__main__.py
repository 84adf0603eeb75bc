"""``python -m benchmarks NAME [OPTIONS]``: run the benchmark NAME (``python -m benchmarks``
lists them; ``python -m benchmarks NAME --help`` shows its options;
``python -m benchmarks check PAGE.md ...`` parses every benchmark command a page shows,
without running it)."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import pkgutil
import runpy
import shlex
import sys
from pathlib import Path
from unittest import mock

import benchmarks

#: Modules that are libraries of the benchmarks, not benchmarks themselves.
LIBRARIES = {"common", "forward.mitsuba_peer"}


def benchmark_names() -> list[str]:
    """Every benchmark as ``area.name`` (the module under :mod:`benchmarks`)."""
    names = []
    for area in pkgutil.iter_modules(benchmarks.__path__):
        if not area.ispkg:
            if area.name not in LIBRARIES and not area.name.startswith("_"):
                names.append(area.name)
            continue
        package = importlib.import_module(f"benchmarks.{area.name}")
        names += [f"{area.name}.{m.name}" for m in pkgutil.iter_modules(package.__path__)
                  if f"{area.name}.{m.name}" not in LIBRARIES]
    return sorted(names)


def summary(name: str) -> str:
    """The first sentence of a benchmark's docstring, without importing cloudct's kernels."""
    spec = importlib.util.find_spec(f"benchmarks.{name}")
    with open(spec.origin, encoding="utf-8") as source:
        text = source.read()
    start = text.find('"""') + 3
    paragraph = text[start:text.find("\n\n", start)].split('"""')[0]
    sentence = " ".join(paragraph.split()).split(". ")[0]
    return sentence.rstrip(".") + "."


class _Parsed(Exception):
    """Raised instead of running a benchmark whose options parsed."""


def page_commands(page: Path) -> list[list[str]]:
    """The ``python -m benchmarks NAME ...`` commands of a Markdown page's code blocks, as
    argument lists (backslash continuations joined, comments dropped); blocks fenced as
    ``text`` hold templates, not commands, and are left out."""
    commands, fence, lines = [], None, page.read_text().replace("\\\n", " ").splitlines()
    for line in lines:
        if line.startswith("```"):
            fence = line[3:].strip() if fence is None else None
            continue
        line = line.split(" #", 1)[0].strip()
        if fence not in (None, "text") and line.startswith("python -m benchmarks "):
            commands.append(shlex.split(line)[3:])
    return commands


def parse_error(argv: list[str]) -> str | None:
    """Why ``python -m benchmarks`` with ``argv`` would not reproduce its recorded run, or
    None. The benchmark is imported and its options parsed, then stopped: an unknown
    benchmark or options its parser refuses are reported; and where the benchmark records
    its retrieval settings (a ``run_config(args)`` function, the result's ``config``) and
    the result file of ``--output`` exists, the settings that today's defaults would change
    (:func:`settings_drift`)."""
    if argv[0] == "scenes" or argv[0] not in benchmark_names():  # scenes writes at parse
        return None if argv[0] == "scenes" else f"no benchmark {argv[0]!r}"
    parse = argparse.ArgumentParser.parse_args
    parsed = []

    def parse_then_stop(parser, args=None, namespace=None):
        parsed.append(parse(parser, args, namespace))
        raise _Parsed

    saved, stderr = sys.argv, io.StringIO()
    try:
        with mock.patch.object(argparse.ArgumentParser, "parse_args", parse_then_stop), \
                contextlib.redirect_stderr(stderr):
            sys.argv = [f"benchmarks.{argv[0]}", *argv[1:]]
            importlib.import_module(f"benchmarks.{argv[0]}").main()
    except _Parsed:
        module = importlib.import_module(f"benchmarks.{argv[0]}")
        drift = settings_drift(module, parsed[0])
        return f"{shlex.join(argv)}: add {drift}" if drift else None
    except SystemExit:
        return f"{shlex.join(argv)}: {stderr.getvalue().strip().splitlines()[-1]}"
    finally:
        sys.argv = saved
    return f"{shlex.join(argv)}: ran without parsing options"


def settings_drift(module, args: argparse.Namespace) -> str:
    """The options that would make ``args`` run the retrieval settings recorded in its
    result file (``args.output``), as a string ("" when they match or nothing is
    recorded). A setting that the run's version of cloudct did not have yet is compared
    with what that version did (:func:`cloudct.retrieval.config_file.config_from_json`)."""
    output = Path(str(getattr(args, "output", "")))
    if not hasattr(module, "run_config") or not output.is_file():
        return ""
    import json

    from cloudct.cli.run_options import OPTION_NAMES
    from cloudct.retrieval.config_file import config_from_json
    from cloudct.retrieval.priors import prior_text

    result = json.loads(output.read_text())
    recorded = result.get("config")
    if recorded is None:
        return ""
    options = []
    # the carved start's profile: recorded since the excess profile became the default
    start = result.get("start", "carved hull" if result.get("date", "") < "2026-11-22 05:00"
                       else "")
    constant = start in ("carved hull", "carved hull, constant profile")
    if constant and getattr(args, "profile", None) != "constant":
        options.append("--profile constant")
    stages = len(recorded["stages"])
    for field, then in (("averaging", "none"), ("sparsity", 0.0),  # settings a run's
                        ("gradient_smoothing", [0.0] * stages),      # version lacked: what
                        ("image_photons", [1.0] * stages)):          # it did without them
        recorded.setdefault(field, then)
    then, now = vars(config_from_json(json.dumps(recorded))), vars(module.run_config(args))
    for settings in (then, now):  # unset: as the medium records; the benchmarks' media
        if settings.get("phase_truncation") is None:  # record no cut, so the full peak
            settings["phase_truncation"] = 0.0
    for field, value in then.items():
        if now.get(field) == value or field not in OPTION_NAMES:
            continue
        if field == "recycle_gradient":  # a flag: --fresh-gradient sets it False
            options.append("--fresh-gradient" if not value else "(without --fresh-gradient)")
        elif value is None:  # an option that was not given
            options.append(f"(without {OPTION_NAMES[field]})")
        else:
            shown = (" ".join(prior_text(p) for p in value) if field == "priors"
                     else " ".join(map(str, value)) if isinstance(value, tuple) else str(value))
            options.append(f"{OPTION_NAMES[field]} {shown}")
    return " ".join(options)


def main(argv: list[str]) -> int:
    names = benchmark_names()
    if argv and argv[0] == "check":
        errors = [e for page in argv[1:] for cmd in page_commands(Path(page))
                  if (e := parse_error(cmd))]
        print("\n".join(errors) or "every command parses")
        return 1 if errors else 0
    if not argv or argv[0] in ("-h", "--help", "list"):
        print(__doc__.strip(), "\n")
        width = max(map(len, names))
        for name in names:
            print(f"  {name:<{width}}  {summary(name)}")
        return 0
    name = argv[0].replace("/", ".").removesuffix(".py")
    if name not in names:
        print(f"no benchmark {argv[0]!r}; one of: {', '.join(names)}", file=sys.stderr)
        return 2
    sys.argv = [f"benchmarks.{name}", *argv[1:]]
    runpy.run_module(f"benchmarks.{name}", run_name="__main__", alter_sys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
