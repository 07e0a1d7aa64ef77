"""The one config schema: strict, frozen pydantic models and one-line errors.

Every table a user writes (``robot.toml``, ``--config``, ``--job-options``) is checked by a model
derived from :class:`Schema`: an integer refuses 25.7, a number refuses a string, a string refuses
a number, floats are finite and inside the range the field declares, unknown keys are refused and
the known ones named. :func:`parse` turns the first problem into one :class:`ConfigError` line
naming the key, the value and what was expected. pydantic v2 in strict mode does the checking
(well kept, fast, typed); this module only fixes the policy and the wording, so every layer
declares its own model (a laser's options in drivers/, SLAM's in fusion/) and says the same.
Import it only where a config is read: pydantic costs ~0.1 s, and ``trundle --help`` stays fast.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar, get_args

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator

from trundle.logs.errors import ConfigError


class Schema(BaseModel):
    """Base of every config model: strict types, frozen, unknown keys refused, floats finite."""

    model_config = ConfigDict(strict=True, frozen=True, extra="forbid", allow_inf_nan=False,
                              validate_default=True)

    @field_validator("*", mode="before")
    @classmethod
    def _exact(cls, value: Any) -> Any:
        """A whole number beyond 2**53 is refused: as a float it would silently become another one."""
        if type(value) is int and abs(value) > 2**53:
            raise ValueError("expected a number of at most 2**53 in size (as a float it would change)")
        return value


M = TypeVar("M", bound=Schema)


def _array_of(count: int, words: str) -> BeforeValidator:
    """A TOML array of ``count`` items becomes a tuple (strict mode refuses a list for a tuple);
    any other value or length is refused as ``expected <words>``."""

    def as_tuple(value: Any) -> Any:
        if not isinstance(value, (list, tuple)) or len(value) != count:
            raise ValueError(f"expected {words}")
        return tuple(value)

    return BeforeValidator(as_tuple)


def _path(value: Any) -> Any:
    """A non-empty string becomes a Path with ``~`` expanded; anything else stays as it is, refused."""
    return Path(value).expanduser() if isinstance(value, str) and value else value


Triple = Annotated[tuple[float, float, float], _array_of(3, "three numbers")]
"""Three finite numbers (a TOML array), e.g. a translation in metres or roll, pitch, yaw in radians."""

Pair = Annotated[tuple[float, float], _array_of(2, "two numbers")]
"""Two finite numbers (a TOML array), e.g. the lower and upper bound of a search window."""

PathValue = Annotated[Path, BeforeValidator(_path)]
"""A path given as a non-empty string."""

Name = Annotated[str, Field(min_length=1)]
"""A non-empty string: a frame id, a topic, a device or joint name."""


def parse(model: type[M], table: Mapping[str, Any] | None, where: str = "") -> M:
    """``model`` built from ``table`` (None: every default), or one ConfigError line.

    ``where`` is the prefix of the key in the message: the file and table, e.g.
    ``robot.toml: slam`` gives ``robot.toml: slam.resolution = '0.05': expected a number``.
    """
    if table is not None and not isinstance(table, Mapping):
        raise ConfigError(f"{where or 'config'} = {table!r}: expected a table")
    try:
        return model.model_validate(dict(table or {}))
    except ValidationError as error:
        raise ConfigError(describe(error, model, where)) from None


def parse_text(model: type[M], table: Mapping[str, Any] | None, text: Mapping[str, str], where: str = "") -> M:
    """``model`` from ``table`` (checked strictly, as :func:`parse`) with ``text`` over it: values
    given as text (URL query parameters), each read as its field's type (``"5"`` is a whole
    number for an integer, a string for a name; ``yes``/``no`` for true or false), or one
    ConfigError line. ``table`` None: the values are all in ``text``."""
    given: dict[str, Any] = {}
    if table is not None:
        base = parse(model, table, where)
        if not text:
            return base
        given = base.model_dump(exclude_unset=True)
    try:
        return model.model_validate({**given, **text}, strict=False)
    except ValidationError as error:
        raise ConfigError(describe(error, model, where)) from None


def _key_path(where: str, loc: tuple[int | str, ...]) -> str:
    """``where`` (``file: table``, or ``file: `` for the whole document) and the key's path in it:
    ``file: table.key[0]``."""
    keys = "".join(f"[{part}]" if isinstance(part, int) else f".{_key(part)}" for part in loc)
    if not where or where.endswith(": "):
        return where + (keys.lstrip(".") or "config")
    return f"{where}{keys}"


def _key(part: str) -> str:
    """A key as the message shows it: bare when plain, quoted otherwise (one line always)."""
    return part if part.replace("_", "").replace("-", "").isalnum() else repr(part)


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The model a field holds, itself or inside a list, tuple or optional (None: not a table)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    return next((m for m in map(_model_in, get_args(annotation)) if m is not None), None)


def _known(model: type[BaseModel], loc: tuple[int | str, ...]) -> list[str]:
    """The keys known in the table at ``loc`` (the parent of an unknown key)."""
    current: type[BaseModel] | None = model
    for part in loc:
        if isinstance(part, int):
            continue  # an item of a list of tables
        field = current.model_fields.get(part) if current is not None else None
        current = _model_in(field.annotation) if field is not None else None
    return sorted(current.model_fields) if current is not None else []


EXPECTED = {
    "int_type": "a whole number", "int_from_float": "a whole number", "float_type": "a number",
    "string_type": "a string", "bool_type": "true or false", "finite_number": "a finite number",
    "tuple_type": "an array", "list_type": "an array", "dict_type": "a table", "model_type": "a table",
    "model_attributes_type": "a table", "path_type": "a path (a non-empty string)",
    "missing": "a value (required)", "is_instance_of": "a path (a non-empty string)",
    "int_parsing": "a whole number", "float_parsing": "a number", "bool_parsing": "true or false",
    "string_too_short": "a non-empty string",
}


def _expected(kind: str, ctx: Mapping[str, Any], message: str) -> str:
    if kind in EXPECTED:
        return EXPECTED[kind]
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()))
        return f"a number {bounds[kind]} {limit:g}" if isinstance(limit, float) else f"a number {bounds[kind]} {limit}"
    if kind == "literal_error":
        return f"one of {ctx.get('expected', '')}".replace("'", "")
    if kind in ("too_short", "too_long"):
        return message.replace("Tuple should have", "").replace("List should have", "").strip() or message
    return message[0].lower() + message[1:] if message else kind


def describe(error: ValidationError, model: type[BaseModel], where: str = "") -> str:
    """The first problem in ``error`` as one line: key, value and what was expected."""
    first = error.errors(include_url=False)[0]
    loc = tuple(first["loc"])
    kind = first["type"]
    if kind == "extra_forbidden":
        known = _known(model, loc[:-1])
        source, _, table_name = where.rpartition(": ")
        table = _key_path(table_name, loc[:-1]) if table_name or loc[:-1] else ""
        scope = f"known in [{table}]" if table and table != "config" else "known"
        tail = f" ({scope}: {', '.join(known)})" if known else ""
        key = _key_path(table_name, loc)
        return f"{source}: unknown key {key}{tail}" if source else f"unknown key {key}{tail}"
    if kind == "value_error" or kind == "assertion_error":
        reason = str(first.get("ctx", {}).get("error", first["msg"]))
        if not loc or isinstance(first["input"], Mapping):  # a check of a whole table: its reason says which
            return f"{_key_path(where, loc)}: {reason}"
        return f"{_key_path(where, loc)} = {first['input']!r}: {reason}"
    expected = _expected(kind, first.get("ctx", {}), first["msg"])
    if kind == "missing":
        return f"{_key_path(where, loc)}: missing, expected {expected}"
    return f"{_key_path(where, loc)} = {first['input']!r}: expected {expected}"
