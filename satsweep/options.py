"""Typed, validated options, and their mapping from TOML files.

Each pipeline stage declares its options as a frozen dataclass deriving from ``Options``; every
field has a default with a one-sentence comment giving its meaning and unit, and a ``check()``
method that raises ``OptionsError`` naming the field. Construction runs the check, so an options
object that exists is valid. ``from_mapping`` builds one from a (TOML) mapping and rejects
unknown keys; the keys a class lists in ``RETIRED`` (options it no longer has) are ignored with
a ``RetiredOptionWarning`` saying what replaced them, so that an older run's config.toml still
loads.

The fields a class lists in ``ADVANCED`` are tuning knobs (their defaults were measured, see
docs/measurements.md): a configuration file gives them in the stage's ``advanced`` sub-table
(``[sweep.advanced]``), or in the stage's own table; ``satsweep config`` shows them apart.

There is no global configuration: options objects are passed explicitly to the stage that uses
them, as COLMAP's ``mvs`` option structs are kept apart from the problem data.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import tomllib
import types
import typing
import warnings
from typing import Any, ClassVar, Mapping, TypeVar

from satsweep.errors import InputError, OptionsError, RetiredOptionWarning

T = TypeVar("T", bound="Options")

# How a TOML file writes None for a field that takes a number or None (``sgm_sweep_gf_radius =
# "none"``); a field that takes a string or None is left out for None (its default is None).
NONE_IN_TOML = "none"


def _none_as_string(expected: Any) -> bool:
    """Whether None is written as NONE_IN_TOML for a field of this type: it admits None and no
    string."""
    args = typing.get_args(expected)
    return type(None) in args and not any(a is str or typing.get_origin(a) is typing.Literal
                                          for a in args)


@dataclasses.dataclass(frozen=True)
class Options:
    """Base of all option dataclasses: validation on construction and mapping from TOML."""

    # The fields that are tuning knobs rather than choices (see the module docstring).
    ADVANCED: ClassVar[tuple[str, ...]] = ()
    # The sub-table of a stage's table that holds its advanced options.
    ADVANCED_TABLE: ClassVar[str] = "advanced"
    # Keys of options the class no longer has -> what replaced them (see the module docstring).
    RETIRED: ClassVar[Mapping[str, str]] = types.MappingProxyType({})

    def __post_init__(self) -> None:
        self._check_types()
        self.check()

    def check(self) -> None:
        """Raise OptionsError naming the field when a value is out of range. Override per stage."""

    # -- helpers for subclasses' check() -------------------------------------------------------
    def _require(self, ok: bool, field: str, why: str) -> None:
        if not ok:
            raise OptionsError(f"{type(self).__name__}.{field} = {getattr(self, field)!r}: {why}")

    def _check_types(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            expected = hints.get(f.name)
            if not _matches(value, expected):
                raise OptionsError(
                    f"{type(self).__name__}.{f.name} = {value!r}: expected {_type_name(expected)}"
                )

    # -- construction from mappings ------------------------------------------------------------
    @classmethod
    def from_mapping(cls: type[T], data: Mapping[str, Any], *, source: str = "options") -> T:
        """Build from a mapping (e.g. a TOML table); unknown keys and wrong types are errors.
        The advanced options may be given in the ``advanced`` sub-mapping or at the top."""
        names = {f.name for f in dataclasses.fields(cls)}
        data = dict(data)
        nested = data.pop(cls.ADVANCED_TABLE, None)
        if nested is not None:
            if not isinstance(nested, Mapping):
                raise OptionsError(f"{source}: '{cls.ADVANCED_TABLE}' must be a table of "
                                   f"advanced options")
            misplaced = sorted(set(nested) - set(cls.ADVANCED) - set(cls.RETIRED))
            if misplaced:
                known = ", ".join(cls.ADVANCED) or "none"
                raise OptionsError(f"{source}: {', '.join(misplaced)} not advanced option(s) of "
                                   f"{cls.__name__} (advanced: {known}; the others go in the "
                                   "stage's own table)")
            twice = sorted(set(nested) & set(data))
            if twice:
                raise OptionsError(f"{source}: {', '.join(twice)} given both in the table and in "
                                   f"its '{cls.ADVANCED_TABLE}' sub-table")
            data.update(nested)
        for key in sorted(set(data) & set(cls.RETIRED)):
            del data[key]
            warnings.warn(f"{source}: {key} is no longer read ({cls.RETIRED[key]}); remove it",
                          RetiredOptionWarning, stacklevel=2)
        unknown = sorted(set(data) - names)
        if unknown:
            raise OptionsError(
                f"{source}: unknown key(s) {', '.join(unknown)} for {cls.__name__} "
                f"(known: {', '.join(sorted(names))})"
            )
        hints = typing.get_type_hints(cls)
        values = {}
        for key, value in data.items():
            expected = hints.get(key)
            # TOML has no tuples: accept a list where a tuple is declared.
            if isinstance(value, list) and typing.get_origin(expected) is tuple:
                value = tuple(value)
            # TOML integers are acceptable where a float is declared.
            if expected is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            # TOML has no null: "none" stands for None where a field takes a number or None.
            if value == NONE_IN_TOML and _none_as_string(expected):
                value = None
            values[key] = value
        try:
            return cls(**values)
        except OptionsError as exc:  # a value out of range: say which file (or flag) gave it
            raise OptionsError(f"{source}: {exc}") from None

    def replace(self: T, **changes: Any) -> T:
        """A copy with some fields changed (validated again); OptionsError for an unknown
        field."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise OptionsError(f"{type(self).__name__} has no option {', '.join(unknown)} "
                               f"(known: {', '.join(sorted(names))})")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def to_tables(self) -> dict[str, Any]:
        """``to_dict`` with the advanced options in their sub-table (the TOML layout), and None
        written as ``NONE_IN_TOML`` where a field takes a number or None (TOML has no null)."""
        flat = self.to_dict()
        hints = typing.get_type_hints(type(self))
        flat = {k: NONE_IN_TOML if v is None and _none_as_string(hints.get(k)) else v
                for k, v in flat.items()}
        basic = {k: v for k, v in flat.items() if k not in self.ADVANCED}
        advanced = {k: flat[k] for k in flat if k in self.ADVANCED}
        return {**basic, self.ADVANCED_TABLE: advanced} if advanced else basic

    @classmethod
    def field_comments(cls) -> dict[str, str]:
        """Each field's comment in the class source: the ``# ...`` after its default and the
        comment lines that continue it, joined. Fields of base classes are searched too; a field
        without a comment (or source that cannot be read) maps to ""."""
        out = {f.name: "" for f in dataclasses.fields(cls)}
        for klass in reversed(cls.__mro__):
            if klass is object or not dataclasses.is_dataclass(klass):
                continue
            out.update({k: v for k, v in _source_comments(klass).items() if k in out and v})
        return out


def _class_source(klass: type) -> str | None:
    """The source of a module-level class: its ``class Name`` line and the lines below it up to
    the next unindented one (``inspect.getsource`` parses the whole module to find a class, about
    40 ms per class of a large module). None when the source cannot be read."""
    import inspect
    import linecache
    import re

    try:
        lines = linecache.getlines(inspect.getsourcefile(klass) or "")
    except TypeError:
        return None
    header = re.compile(rf"class {re.escape(klass.__name__)}\b")
    start = next((i for i, line in enumerate(lines) if header.match(line)), None)
    if start is None:
        return None
    end = start + 1
    while end < len(lines) and (not lines[end].strip() or lines[end][0] in " \t#"):
        end += 1
    return "".join(lines[start:end])


@functools.lru_cache(maxsize=None)
def _source_comments(klass: type) -> dict[str, str]:
    """{field: comment} from the class body's source (see Options.field_comments), read once per
    class (tokenising the sources took about 0.25 s of every run's config.toml).

    Two styles are read: a comment after the field's default, continued by comment lines right
    below it; or comment lines right above a field that has none after its default.
    """
    import io
    import keyword
    import tokenize

    source = _class_source(klass)
    if source is None:
        return {}
    out: dict[str, str] = {}
    body_indent = None
    logical: list = []
    pending: list[str] = []  # own-line comments not yet attached
    last_field = None  # the field whose trailing comment own-line comments may continue
    previous_was_comment = False
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT and not logical:
            text = tok.string.lstrip("#").strip()
            if last_field is not None:
                out[last_field] += " " + text
            else:
                pending.append(text)
            previous_was_comment = True
        elif tok.type == tokenize.NL and not logical:
            if not previous_was_comment:  # a blank line ends both kinds of comment block
                last_field, pending = None, []
            previous_was_comment = False
        elif tok.type == tokenize.NEWLINE:
            first = logical[0] if logical else None
            if body_indent is None and first is not None and first.start[1] > 0:
                body_indent = first.start[1]
            is_field = (first is not None and first.type == tokenize.NAME
                        and not keyword.iskeyword(first.string) and first.start[1] == body_indent
                        and len(logical) > 1 and logical[1].string == ":")
            trailing = [t.string.lstrip("#").strip() for t in logical if t.type == tokenize.COMMENT]
            last_field = None
            if is_field:
                if trailing:
                    out[first.string] = " ".join(trailing)
                    last_field = first.string
                elif pending:
                    out[first.string] = " ".join(pending)
            pending, logical, previous_was_comment = [], [], False
        elif tok.type not in (tokenize.INDENT, tokenize.DEDENT, tokenize.ENCODING):
            logical.append(tok)
    return out


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML file into a dict; a missing or malformed file is an InputError naming it."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(path, "config file does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML: {exc}") from None


def dumps_toml(tables: Mapping[str, Mapping[str, Any]],
               comments: Mapping[str, Mapping[str, str]] | None = None,
               headers: Mapping[str, str] | None = None) -> str:
    """Serialise {table: {key: value}} of plain values (numbers, strings, bools, lists) as TOML;
    a value that is itself a mapping is written as the sub-table ``[table.key]`` after the
    table's own keys. ``comments[table][key]``, where given, is written as ``#`` lines above the
    key (the sub-table's keys take their comments from the table's), and ``headers[name]``
    above a (sub-)table."""
    import textwrap

    def wrap(text: str) -> list[str]:
        return textwrap.wrap(text, width=98, initial_indent="# ", subsequent_indent="# ",
                             break_on_hyphens=False)

    lines: list[str] = []

    def table(name: str, values: Mapping[str, Any], notes: Mapping[str, str]) -> None:
        if (headers or {}).get(name):
            lines.extend(wrap(headers[name]))
        lines.append(f"[{name}]")
        subs = {k: v for k, v in values.items() if isinstance(v, Mapping)}
        for key, value in values.items():
            if key in subs:
                continue
            if notes.get(key):
                lines.extend(wrap(notes[key]))
            if value is None:
                lines.append(f"# {key} is unset")
                continue
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
        for key, value in subs.items():
            table(f"{name}.{key}", value, notes)

    for name, values in tables.items():
        table(name, values, (comments or {}).get(name, {}))
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def _matches(value: Any, expected: Any) -> bool:
    if expected is None or expected is Any:
        return True
    origin = typing.get_origin(expected)
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        return any(_matches(value, arg) for arg in typing.get_args(expected))
    if origin is typing.Literal:
        return value in typing.get_args(expected)
    if expected is type(None):
        return value is None
    if origin is tuple:
        args = typing.get_args(expected)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(args) == len(value) and all(_matches(v, a) for v, a in zip(value, args))
    if expected is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if expected is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(expected, type):
        return isinstance(value, expected)
    return True


def _type_name(expected: Any) -> str:
    if typing.get_origin(expected) is typing.Literal:
        return "one of " + ", ".join(repr(v) for v in typing.get_args(expected))
    return getattr(expected, "__name__", None) or str(expected).replace("typing.", "")
