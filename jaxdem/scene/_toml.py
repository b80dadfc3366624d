"""Scene files and TOML text -> a plain dict, before any validation.

Reads at most ``MAX_FILE_BYTES`` (+1) bytes, accepts a byte-order mark, refuses an
unreadable, binary, empty or oversized file, and turns a TOML syntax error into a
``SceneError``: a key or table given twice names its dotted path and line. The dict goes
to :func:`jaxdem.scene._overrides.apply_overrides` (``--set``) and then to
:func:`jaxdem.scene.parse_scene`.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from jaxdem.scene._fields import SceneError

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib


MAX_FILE_BYTES = 64 * 2**20
"""Largest scene file read (64 MiB; a 10,000-block scene is about 1 MiB)."""


def read_toml(path: Path) -> dict:
    name = str(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)  # bounded: /dev/zero or a huge file
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise SceneError(name, f"cannot read scene file ({reason})") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise SceneError(name, f"scene file is larger than {MAX_FILE_BYTES // 2**20} MiB")
    try:
        text = raw.decode("utf-8-sig")  # -sig: a byte-order mark some editors write
    except UnicodeDecodeError as exc:
        raise SceneError(name, f"scene file is not UTF-8 text ({exc.reason})") from exc
    if not text.strip():
        raise SceneError(name, "scene file is empty")
    data = parse_toml(text, name)
    if not data:
        raise SceneError(name, "scene file is empty (only comments)")
    return data


def parse_toml(text: str, source: str) -> dict:
    """TOML text -> dict; a syntax error, a key or table given twice, or an integer too
    long to read is a SceneError (a duplicate names the field path and the line)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _toml_error(str(exc), text, source) from None
    except ValueError as exc:  # e.g. an integer of more than 4,300 digits
        raise SceneError(source, f"invalid TOML ({exc})") from None


_HEADER = re.compile(r"^\s*(\[\[?)\s*([^\]]+?)\s*\]\]?")
_KEY = re.compile(r"^\s*([^=\[#]+?)\s*=")


def _toml_error(message: str, text: str, source: str) -> SceneError:
    """A TOML decode error as a SceneError; a key or table declared twice names its path."""
    at = re.search(r"\(at line (\d+), column \d+\)$", message)
    twice = re.match(r"Cannot declare (\(.*\)) twice", message)
    if at and twice:
        keys = ast.literal_eval(twice.group(1))
        return SceneError(".".join(map(str, keys)),
                          f"duplicate table: declared twice ({source}, line {at.group(1)})")
    if at and message.startswith("Cannot overwrite a value"):
        line = int(at.group(1))
        lines = text.splitlines()
        key = _KEY.match(lines[line - 1]) if line <= len(lines) else None
        if key:
            table: list[str] = []
            counts: dict[str, int] = {}
            for row in lines[: line - 1]:
                header = _HEADER.match(row)
                if header:
                    name = _dotted(header.group(2))
                    table = [name]
                    if header.group(1) == "[[":
                        counts[name] = counts.get(name, -1) + 1
                        table.append(str(counts[name]))
            path = ".".join([*table, _dotted(key.group(1))])
            return SceneError(path, f"duplicate key: given twice ({source}, line {line})")
    return SceneError(source, f"invalid TOML ({message})")


def _dotted(key: str) -> str:
    """A TOML key as written (``a . "b"``) -> dotted path ``a.b`` (for messages)."""
    return ".".join(part.strip().strip("\"'") for part in key.split("."))
