"""The jobs the fleet runs, their options, and one call of a job on one log.

Each job is a one-log function of :mod:`trundle.tools.jobs` (the code of the single-log command).
The fleet sets the log, the outputs (in the log's own folder) and the progress; every other
parameter is a job option, given as ``KEY=VALUE`` and converted by the parameter's type hint, so
a parameter a job gains is a fleet option with no change here. Values: paths (made absolute;
they must exist and be visible to every node), numbers, ``true``/``false``, comma-separated
lists, and tables (a TOML file, e.g. ``config=robot.toml``, or inline JSON ``{...}``; a robot config is
checked by the one validator, :func:`trundle.tools.config.robot.parse_config`, before any task starts).
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from trundle import __version__
from trundle.logs.errors import ConfigError, UserError
from trundle.tools.config.robot import RobotConfig, parse_config, read_toml


@dataclass(frozen=True)
class Job:
    """A one-log job: its function (``module:name``), where each output parameter points,
    relative to the log's output folder (``"."`` is the folder itself), and the options whose
    values come from a list (option -> ``module:name`` of the function giving the choices), so a
    bad choice is refused before any task starts."""

    function: str
    outputs: Mapping[str, str] = field(default_factory=dict)
    choices: Mapping[str, str] = field(default_factory=dict)


JOBS: dict[str, Job] = {
    "info": Job("trundle.tools.jobs.info:info_log"),
    "slam": Job("trundle.tools.jobs.slam:slam_log", {"output": "."},
                {"estimator": "trundle.fusion.slam.estimators:choices"}),
    "localize": Job("trundle.tools.jobs.localize:localize_log", {"trajectory_csv": "trajectory.csv"}),
    "perceive": Job("trundle.tools.jobs.perceive:perceive_log", {"output": "perceive.mcap"}),
    "characterize": Job("trundle.tools.jobs.characterize:characterize_log", {"output": "."}),
}
FLEET_SET = {"log", "progress"}   # parameters the fleet always sets (besides each job's outputs)
REPORT = "report.json"            # the job's report in every log's folder


def _load(reference: str) -> Any:
    """The object a ``module:name`` reference names (its module imported now)."""
    module, name = reference.split(":")
    return getattr(importlib.import_module(module), name)


def job_function(job: str) -> Callable[..., dict[str, Any]]:
    """The one-log function of ``job`` (imported now, so only the jobs that run are loaded)."""
    if job not in JOBS:
        raise UserError(f"unknown job {job!r} (choose from {', '.join(JOBS)})")
    return _load(JOBS[job].function)


def option_choices(job: str, name: str) -> tuple[str, ...] | None:
    """The values option ``name`` of ``job`` may take (None: any of its kind)."""
    reference = JOBS[job].choices.get(name)
    return None if reference is None else tuple(_load(reference)())


def _kind(hint: Any) -> str | None:
    """What a parameter's type hint takes from the command line (None: not settable there)."""
    members = [a for a in typing.get_args(hint) if a is not type(None)] \
        if typing.get_origin(hint) in (typing.Union, types.UnionType) else [hint]
    origins = [typing.get_origin(a) or a for a in members]
    if any(o is Path for o in origins):
        return "path"
    if RobotConfig in origins:
        return "config"
    if any(isinstance(o, type) and issubclass(o, Mapping) for o in origins):
        return "table"
    if any(o in (list, tuple) or (isinstance(o, type) and o is not str and issubclass(o, Sequence))
           for o in origins):
        return "list"
    for kind, wanted in (("bool", {bool}), ("int-or-text", {int, str}), ("float", {float}), ("int", {int}),
                         ("text", {str})):
        if wanted <= set(origins):
            return kind
    return None


def parameters(job: str) -> dict[str, tuple[str, Any]]:
    """The options of ``job``: name -> (kind, default; ``inspect.Parameter.empty`` if required)."""
    function = job_function(job)
    hints = typing.get_type_hints(function)
    fixed = FLEET_SET | set(JOBS[job].outputs)
    options = {}
    for name, p in inspect.signature(function).parameters.items():
        kind = _kind(hints.get(name))
        if name not in fixed and kind is not None:
            options[name] = (kind, p.default)
    return options


def describe(job: str) -> str:
    """The options of ``job`` as ``name=default (kind)``, ``name=...`` for a required one."""
    return ", ".join(f"{name}={'...' if default is inspect.Parameter.empty else repr(default)} ({kind})"
                     for name, (kind, default) in parameters(job).items())


def _convert(job: str, name: str, kind: str, text: str) -> Any:
    """The JSON-able value of option ``name`` from its command-line ``text``; a bad value is a UserError."""
    where = f"{job} option {name}"
    if kind == "path":
        path = Path(text).expanduser().resolve()
        if not path.exists():
            raise UserError(f"{where}: no such file or folder: {text}")
        return str(path)
    if kind in ("table", "config"):
        if text.lstrip().startswith("{"):
            try:
                value = json.loads(text)
            except json.JSONDecodeError as error:
                raise UserError(f"{where}: invalid JSON ({error})") from None
            if not isinstance(value, dict):
                raise UserError(f"{where}: needs a JSON object")
        else:
            value = read_toml(Path(text).expanduser())
        if kind == "config":
            parse_config(value, where)  # a robot config is refused here, in one line, not on every worker
        return value
    if kind == "list":
        return [item for item in text.split(",") if item]
    return _scalar(job, name, kind, text)


def _scalar(job: str, name: str, kind: str, text: str) -> Any:
    """A number, true/false or text option read by the one config schema (text read as the
    option's type: an integer refuses 1.5, a number refuses nan and words)."""
    from pydantic import Field, create_model  # pydantic only once an option is read

    from trundle.logs.schema import Schema, parse_text

    annotations: dict[str, Any] = {"bool": bool, "int": int, "float": float, "text": str,
                                   "int-or-text": Annotated[int | str, Field(union_mode="left_to_right")]}
    fields: dict[str, Any] = {name: (annotations[kind], ...)}
    model = create_model("JobOption", __base__=Schema, **fields)
    try:
        return getattr(parse_text(model, None, {name: text}), name)
    except ConfigError as error:
        raise ConfigError(f"{job} option {error}") from None


def parse_options(job: str, items: Sequence[str]) -> dict[str, Any]:
    """The ``KEY=VALUE`` items as the job's keyword arguments (JSON-able); unknown, repeated or
    missing required options are a UserError that lists the job's options."""
    known = parameters(job)
    listing = describe(job)
    options: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise UserError(f"--job-options needs KEY=VALUE, got {item!r}")
        if name not in known:
            raise UserError(f"{job} has no option {name!r} (options: {listing or 'none'})")
        if name in options:
            raise UserError(f"{job} option {name} given twice")
        options[name] = _convert(job, name, known[name][0], text)
        allowed = option_choices(job, name)
        if allowed is not None and options[name] not in allowed:
            raise ConfigError(f"{job} option {name} = {text!r}: expected one of {', '.join(allowed)}")
    missing = [n for n, (_, d) in known.items() if d is inspect.Parameter.empty and n not in options]
    if missing:
        raise UserError(f"{job} needs {', '.join(f'{n}=...' for n in missing)} in --job-options (options: {listing})")
    return options


def _digest(path: Path) -> str:
    """SHA-256 of a file, or of a folder's file names and contents (sorted)."""
    h = hashlib.sha256()
    for f in sorted(p for p in ([path] if path.is_file() else path.rglob("*")) if p.is_file()):
        h.update(str(f.relative_to(path) if f != path else "").encode() + b"\0")
        with open(f, "rb") as stream:
            h.update(hashlib.file_digest(stream, "sha256").digest())
    return h.hexdigest()


def options_key(job: str, options: Mapping[str, Any]) -> str:
    """A hash of what decides a result besides the log: the job, its options, the contents of
    the files they name (a map, a reference) and the trundle version."""
    kinds = parameters(job)
    inputs = {n: _digest(Path(v)) for n, v in options.items() if kinds[n][0] == "path"}
    text = json.dumps({"job": job, "options": options, "inputs": inputs, "version": __version__},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def run_job(job: str, log: Path, folder: Path, options: Mapping[str, Any]) -> dict[str, Any]:
    """Run ``job`` on ``log`` with its outputs in ``folder`` (created); returns the job's report."""
    kinds = parameters(job)
    kwargs = {n: Path(v) if kinds[n][0] == "path" else v for n, v in options.items()}
    kwargs.update({n: folder / rel if rel != "." else folder for n, rel in JOBS[job].outputs.items()})
    folder.mkdir(parents=True, exist_ok=True)
    return job_function(job)(log, **kwargs)
