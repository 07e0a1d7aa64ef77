"""Writing a robot configuration as TOML text (how the demo and tests make one): the standard
library reads TOML but does not write it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (str, Path)):
        return json.dumps(str(value), ensure_ascii=False).replace("\x7f", "\\u007f")  # a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def format_config(tables: dict[str, Any]) -> str:
    """TOML text for ``{table: {key: value}}`` (lists of tables as ``[[table]]``);
    ``parse_config(tomllib.loads(text))`` reads it back."""
    lines: list[str] = []
    for name, table in tables.items():
        for item in table if isinstance(table, list) else [table]:
            lines.append(f"[[{name}]]" if isinstance(table, list) else f"[{name}]")
            nested = {k: v for k, v in item.items() if isinstance(v, dict)}
            lines += [f"{key} = {_toml_value(value)}" for key, value in item.items() if key not in nested]
            for key, sub in nested.items():
                lines.append(f"[{name}.{key}]")
                lines += [f"{k} = {_toml_value(v)}" for k, v in sub.items()]
            lines.append("")
    return "\n".join(lines)
