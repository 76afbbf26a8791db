"""The one base of every configuration file: error type, strict model, field types, and
safe reading of YAML files.

Scene files (:mod:`mysim_jax.config.scene`, with its ``contact:`` and ``quadrotors:`` blocks)
and gains files all build on this module, so every file is held to the same rules:

* **Reading** (:func:`read_yaml_file`, :func:`parse_yaml`): the file must exist, be a
  regular file, be at most :data:`MAX_FILE_BYTES`, and be UTF-8 text (a UTF-8 byte-order
  mark is allowed; UTF-16/32, binary data and other encodings are errors naming the file).
  The YAML may not repeat a key in one mapping (PyYAML would silently keep the last one),
  nest deeper than :data:`MAX_NESTING` levels, or expand (through anchors and aliases) to
  more than :data:`MAX_YAML_VALUES` values.
* **Models** (:class:`StrictModel`): unknown keys are errors, models are frozen, and a YAML
  boolean (``true``, ``yes``, ``on``, ...) is never read as a number (pydantic would read
  ``mass: true`` as 1.0).
* **Numbers** (:data:`Finite`, :data:`PosFloat`, :data:`NonNegFloat`, :data:`Tolerance`):
  finite, at most :data:`MAX_MAGNITUDE` in magnitude, and strictly positive quantities at
  least :data:`MIN_POSITIVE`. SI values outside these bounds describe nothing a drone-net
  scene contains, and they overflow (or underflow to zero) once multiplied in float32,
  whose range ends at 3.4e38 (1.2e-38 for normal numbers).

This module imports pydantic and PyYAML only: validating a file never imports JAX.
"""

from __future__ import annotations

import math
import os
import re
import stat
import typing
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

# Largest magnitude of any number in a configuration file (SI units).
MAX_MAGNITUDE = 1e12
# Smallest value of a strictly positive physical quantity (mass, length, stiffness, time step...).
MIN_POSITIVE = 1e-12
# Deepest nesting of YAML collections accepted in a file (scene files need about 6).
MAX_NESTING = 64
# Most values a YAML document may expand to (anchors and aliases included).
MAX_YAML_VALUES = 1_000_000
# Largest configuration file read (scene files are a few kB).
MAX_FILE_BYTES = 16 * 1024 * 1024


class ConfigError(ValueError):
    """A configuration is invalid. The message names every offending field or file."""


# --- numbers ---------------------------------------------------------------------------


def _bounded(value: float) -> float:
    if abs(value) > MAX_MAGNITUDE:
        raise ValueError(
            f"{value:g} is beyond the accepted magnitude {MAX_MAGNITUDE:g} (SI units): no drone-net "
            "scene needs it, and products of such numbers overflow float32 (max 3.4e38)"
        )
    return value


def _bounded_positive(value: float) -> float:
    if value < MIN_POSITIVE:
        raise ValueError(
            f"{value:g} is below the smallest accepted positive value {MIN_POSITIVE:g} (SI units): "
            "it underflows float32 arithmetic (dividing by it gives inf)"
        )
    return _bounded(value)


Finite = Annotated[float, Field(allow_inf_nan=False), AfterValidator(_bounded)]
PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False), AfterValidator(_bounded_positive)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False), AfterValidator(_bounded)]
# relative / absolute tolerances of adaptive solvers (may be tiny, never >= 1)
Tolerance = Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
Vec4 = tuple[Finite, Finite, Finite, Finite]
NonNegVec3 = tuple[NonNegFloat, NonNegFloat, NonNegFloat]
PosVec4 = tuple[PosFloat, PosFloat, PosFloat, PosFloat]
Pair = tuple[Finite, Finite]
PosPair = tuple[PosFloat, PosFloat]
Name = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")]


def unit_quaternion(q) -> tuple[float, float, float, float]:
    """``q / |q|``, computed without overflow or underflow (scaled by its largest entry)."""
    big = max(abs(c) for c in q)
    if big == 0.0:
        raise ValueError("quaternion [w, x, y, z] must be non-zero")
    scaled = [c / big for c in q]
    n = math.sqrt(sum(c * c for c in scaled))
    return tuple(c / n for c in scaled)


UnitQuat = Annotated[Vec4, AfterValidator(unit_quaternion)]


# --- the strict model ------------------------------------------------------------------


class _Boolean:
    """Stands in for a YAML boolean given where the field expects no boolean, so that the
    field's own validator rejects it and the error carries the field's path."""

    def __init__(self, value: bool):
        self.value = value

    def __repr__(self) -> str:
        return f"the boolean {str(self.value).lower()}: YAML reads true/false/yes/no/on/off as booleans"


def _accepts_bool(annotation) -> bool:
    if annotation is bool:
        return True
    if typing.get_origin(annotation) is typing.Literal:
        return any(isinstance(a, bool) for a in typing.get_args(annotation))
    return any(_accepts_bool(a) for a in typing.get_args(annotation))


def _mark_booleans(value):
    if isinstance(value, bool):
        return _Boolean(value)
    if isinstance(value, (list, tuple)):
        return [_mark_booleans(v) for v in value]
    return value          # mappings are nested models: they check their own fields


class StrictModel(BaseModel):
    """Base of every configuration model: unknown keys are errors, instances are frozen,
    and booleans are accepted only by fields declared ``bool``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _no_booleans_as_numbers(cls, data):
        if not isinstance(data, dict):
            return data
        fields = cls.model_fields
        out = dict(data)
        for key, value in data.items():
            field = fields.get(key)
            if field is not None and not _accepts_bool(field.annotation):
                out[key] = _mark_booleans(value)
        return out


# the names pydantic gives the members of a union in an error's location (field names
# are snake_case words, never these)
_PLAIN_TAGS = {"int", "float", "str", "bool", "none", "list", "dict", "tuple"}
_TAG_PREFIXES = ("constrained-", "function-", "lax-or-strict", "json-or-python", "tagged-union", "is-instance",
                 "literal[", "nullable[")


def _readable_tag(tag: str) -> str:
    """A union member's schema name as a reader would say it: validators dropped, tuples of
    numbers counted (``tuple[function-after[_bounded(), float], ...]`` -> ``3 numbers``)."""
    prev = None
    while prev != tag:
        prev = tag
        tag = re.sub(r"function-(?:after|before|wrap|plain)\[[^\[\]]*?,\s*([^\[\]]+?)\]", r"\1", tag)
    tag = re.sub(r"constrained-(int|float)", r"\1", tag)
    tag = re.sub(r"^literal\[(.*)\]$", r"\1", tag)
    tag = re.sub(r"tuple\[(float(?:, float)*)\]", lambda m: f"{m.group(1).count('float')} numbers", tag)
    return re.sub(r"tuple\[((\d+) numbers(?:, \2 numbers)*)\]",
                  lambda m: f"{m.group(1).count('numbers')} x {m.group(2)} numbers", tag)


def _split_location(loc) -> tuple[list[str], list[str]]:
    """The path as the user wrote it, and the union members the error went through."""
    path, members = [], []
    for part in loc:
        part = str(part)
        if "[" in part or "(" in part or part in _PLAIN_TAGS or part.startswith(_TAG_PREFIXES):
            members.append(_readable_tag(part))
        else:
            path.append(part)
    return path, members


def format_validation_error(err: ValidationError) -> str:
    """One line per problem: ``dotted.path: message (got value)``; an error inside one
    member of a union (a value that may be written in several forms) says which form
    it was read as: ``bodies.0.inertia (as 3 numbers): too few entries``."""
    lines = []
    for e in err.errors():
        loc, members = _split_location(e["loc"])
        kind, msg = e["type"], e["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        shown = ""
        if kind == "extra_forbidden":
            msg = "unknown key"
        elif kind == "missing" and loc and loc[-1].isdigit():
            msg = f"too few entries (entry {loc[-1]} is missing)"
            loc = loc[:-1]
        elif kind == "too_long":
            msg = "too many entries"
        elif kind not in ("missing", "value_error") and not isinstance(e.get("input"), (dict, list)):
            shown = f" (got {_short(e['input'])})"
        form = f" (as {', '.join(members)})" if members else ""
        if not loc:  # whole-model checks already name their fields
            lines.extend(f"  {part}" for part in msg.split("; "))
        else:
            lines.append(f"  {'.'.join(loc)}{form}: {msg}{shown}")
    return "\n".join(lines)


def _short(value, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --- YAML ------------------------------------------------------------------------------


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing duplicate keys and runaway nesting."""

    _depth = 0

    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > MAX_NESTING:
                raise yaml.composer.ComposerError(
                    None, None, f"collections nested deeper than {MAX_NESTING} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:       # an unhashable key: PyYAML reports it below
                    continue
                if first is not None:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark,
                        f"found duplicate key {key!r} (first given on line {first + 1})", key_node.start_mark)
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


def _count_values(data, limit: int) -> int:
    """Number of values in a parsed document (aliases counted each time they appear),
    counting at most ``limit + 1``."""
    count, stack = 0, [data]
    while stack:
        item = stack.pop()
        count += 1
        if count > limit:
            break
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
    return count


def parse_yaml(text: str, source: str, what: str = "config file") -> Any:
    """Parse YAML text with the strict loader. Raises :class:`ConfigError` naming ``source``
    (a file name, or e.g. ``--set key``) and ``what`` it is."""
    loader = None
    try:
        loader = _StrictLoader(text)
        loader.name = source        # error marks name the file, not "<unicode string>"
        data = loader.get_single_data()
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: broken YAML in the {what}: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{source}: broken YAML in the {what}: nested too deeply") from None
    finally:
        if loader is not None:
            loader.dispose()
    if _count_values(data, MAX_YAML_VALUES) > MAX_YAML_VALUES:
        raise ConfigError(
            f"{source}: the YAML of the {what} expands to more than {MAX_YAML_VALUES:,} values (through "
            "anchors and aliases?): too large")
    return data


_BOMS = ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
         (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16"))


def read_text_file(path: str | Path, what: str = "config file") -> str:
    """Read ``path`` as UTF-8 text. Raises :class:`ConfigError` naming the file and saying
    what is wrong with it (missing, a directory or device, unreadable, too large, binary,
    not UTF-8)."""
    if os.fspath(path).strip() == "":          # Path("") would be "." (a directory)
        raise ConfigError(f"empty path given for the {what}: name a YAML file")
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such {what}") from None
    except NotADirectoryError:
        raise ConfigError(f"{path}: no such {what} (a part of the path is not a directory)") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot access the {what}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"{path}: is a directory, not a {what}")
    if not stat.S_ISREG(info.st_mode):
        raise ConfigError(f"{path}: is not a regular file (a device, pipe or socket), not a {what}")
    if info.st_size > MAX_FILE_BYTES:
        raise ConfigError(f"{path}: {info.st_size:,} bytes is too large for a {what} "
                          f"(at most {MAX_FILE_BYTES:,})")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    for bom, name in _BOMS:
        if data.startswith(bom):
            raise ConfigError(f"{path}: the {what} is {name} text; save it as UTF-8")
    if b"\x00" in data:
        raise ConfigError(f"{path}: binary data (NUL bytes), not a {what} (YAML text, UTF-8)")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}); a {what} "
            "is a YAML text file in UTF-8") from None
    return text


def read_yaml_file(path: str | Path, what: str = "config file") -> Any:
    """Read and parse a YAML file (see the module docstring for what is refused)."""
    return parse_yaml(read_text_file(path, what), str(path), what)


def available_memory_bytes() -> int | None:
    """Memory the machine can still give (Linux ``MemAvailable``; elsewhere the free
    physical pages), or None when it cannot be read."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
