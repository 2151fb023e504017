"""Command lines read into a dataclass (tyro) with every refusal one ``error: ...`` line naming its flag.

tyro answers a bad choice, a bad number or an unknown flag with a box of several lines, and takes a flag given
twice as its last value without a word. :func:`check_argv` finds those mistakes first, from the dataclass's field
types; :func:`cli` runs it, then tyro, and folds whatever tyro still refuses into one line. Every command of the
toolkit reads its flags through :func:`cli`; it lives here, in ``tasks``, the lowest package with commands of its
own (``task-floors``, ``robot-snapshots``), so that every package above can import it. The module itself
needs no torch, and ``tasks/__init__`` loads its torch-bound names at first use, so importing it loads none: a
command's flags are checked before torch is imported.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import io
import os
import re
import sys
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NoReturn, TypeVar, Union

__all__ = ["fail", "scan", "check_argv", "cli", "Given", "usable_cores"]

T = TypeVar("T")


def fail(msg: str) -> NoReturn:
    """The one line every refusal is: ``error: msg`` on stderr, exit status 2."""
    print(f"error: {msg}", file=sys.stderr)
    raise SystemExit(2)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity): what a --threads above it would wait for."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity outside Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Given:
    """One flag of a command line as typed: ``--num-envs 8`` -> spelling "--num-envs", key "num-envs", values
    ("8",); ``--no-progress`` -> key "no-progress"; ``--out=x`` -> values ("x",), inline True."""

    spelling: str
    key: str
    values: tuple[str, ...]
    inline: bool = False


def _is_flag(token: str) -> bool:
    return (token.startswith("--") and token != "--") or token == "-h"


def scan(argv: Sequence[str]) -> list[Given]:
    """The flags of ``argv`` in order, each with the tokens up to the next flag (no types known: what a variadic
    flag would take); tokens before the first flag (positional arguments) and everything after ``--`` are left
    out."""
    out: list[Given] = []
    argv = list(argv)
    i = 0
    while i < len(argv) and argv[i] != "--":
        token = argv[i]
        if not _is_flag(token):
            i += 1
            continue
        spelling, eq, inline = token.partition("=")
        j = i + 1
        while j < len(argv) and not _is_flag(argv[j]) and argv[j] != "--":
            j += 1
        values = (inline, *argv[i + 1:j]) if eq else tuple(argv[i + 1:j])
        out.append(Given(spelling, spelling[2:].replace("_", "-"), values, bool(eq)))
        i = j
    return out


def wants_help(argv: Sequence[str]) -> bool:
    return any(g.spelling in ("--help", "-h") for g in scan(argv))


# ------------------------------------------------------------------------------------------ field types
@dataclass(frozen=True)
class _Field:
    """What a flag accepts: ``kind`` "bool" (a switch, with --no-), "one" (one value), "many" (any number),
    "fixed" (exactly ``len(elements)``) or "any" (not checked here); each element "int", "float", a tuple of
    choices, or None (any text); ``none``: the value None is accepted."""

    name: str
    kind: str
    elements: tuple = ()
    none: bool = False


def _element(tp: Any) -> Any:
    tp = _strip_annotated(tp)[0]
    if tp is int:
        return "int"
    if tp is float:
        return "float"
    if typing.get_origin(tp) is Literal:
        return tuple(str(c) for c in typing.get_args(tp))
    return None


def _strip_annotated(tp: Any) -> tuple[Any, tuple]:
    if typing.get_origin(tp) is typing.Annotated:
        base, *meta = typing.get_args(tp)
        inner, more = _strip_annotated(base)
        return inner, (*meta, *more)
    return tp, ()


def _describe(name: str, tp: Any) -> _Field:
    none = False
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        none = len(args) < len(typing.get_args(tp))
        if len(args) != 1:
            return _Field(name, "any")
        tp = _strip_annotated(args[0])[0]
    if tp is bool:
        return _Field(name, "bool", none=none)
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return _Field(name, "many", (_element(args[0]),), none)
        return _Field(name, "fixed", tuple(_element(a) for a in args), none)
    if typing.get_origin(tp) in (list, set, dict) or dataclasses.is_dataclass(tp):
        return _Field(name, "any", none=none)
    return _Field(name, "one", (_element(tp),), none)


def _fields(cls: type) -> tuple[dict[str, _Field], bool]:
    """{flag key: field} of a dataclass, its switches' --no- forms included, and whether it has positional
    fields."""
    import tyro

    positional = typing.get_args(tyro.conf.Positional[int])[1]
    hints = typing.get_type_hints(cls, include_extras=True)
    flags: dict[str, _Field] = {}
    has_positional = False
    for f in dataclasses.fields(cls):
        tp, meta = _strip_annotated(hints[f.name])
        if any(m is positional for m in meta):
            has_positional = True
            continue
        names = [f.name.replace("_", "-")]
        for m in meta:  # tyro.conf.arg(name=..., aliases=...)
            if getattr(m, "name", None):
                names = [m.name.replace("_", "-")]
            aliases = getattr(m, "aliases", None) or ()
            names += [a.lstrip("-").replace("_", "-") for a in aliases if a.startswith("--")]
        field = _describe(f.name, tp)
        for n in names:
            flags[n] = field
            if field.kind == "bool":
                flags["no-" + n] = field
    return flags, has_positional


def _bad_value(value: str, element: Any, none: bool) -> str | None:
    """Why ``value`` is not one ``element`` (None: it is)."""
    if none and value == "None":
        return None
    if element == "int":
        try:
            int(value)
        except ValueError:
            return f"must be an integer, got {value!r}"
    elif element == "float":
        try:
            float(value)
        except ValueError:
            return f"must be a number, got {value!r}"
    elif isinstance(element, tuple) and value not in element:
        return f"{value!r} is not one of {', '.join(element)}"
    return None


def check_argv(cls: type, argv: Sequence[str], prog: str | None = None) -> None:
    """ValueError naming the flag, as typed, of the first mistake in ``argv`` for the dataclass ``cls``: a flag it
    does not have (with the nearest it has), one given twice (``--x`` and ``--no-x`` included), a value that is
    not one of the flag's choices or not a number of its kind, a missing value. What this does not recognise is
    left to tyro (:func:`cli` folds tyro's answer into one line too)."""
    if wants_help(argv):
        return
    flags, has_positional = _fields(cls)
    seen: dict[str, str] = {}
    for g in scan(argv):
        field = flags.get(g.key)
        if field is None:
            near = difflib.get_close_matches(g.key, list(flags), n=1, cutoff=0.6)
            hint = f" (did you mean --{near[0]}?)" if near else ""
            raise ValueError(f"{g.spelling}: no such flag{hint}; {prog or 'the command'} --help lists them")
        if field.name in seen:
            first = seen[field.name]
            what = "is given twice: give it once" if first == g.spelling else f"and {first} are both given: give one"
            raise ValueError(f"{g.spelling} {what}"
                             + (" (several values after one flag)" if field.kind == "many" else ""))
        seen[field.name] = g.spelling
        values = g.values
        if field.kind == "bool":
            if g.inline:
                raise ValueError(f"{g.spelling} is a switch and takes no value (--{field.name.replace('_', '-')}"
                                 f" or --no-{field.name.replace('_', '-')})")
            continue
        if field.kind == "any":
            continue
        if field.kind == "one":
            if not values:
                raise ValueError(f"{g.spelling} needs a value")
            if len(values) > 1 and not has_positional:
                raise ValueError(f"{g.spelling} takes one value, got {len(values)}: {' '.join(values)}")
            values = values[:1]
        elif field.kind == "fixed" and not (field.none and values == ("None",)):
            if len(values) < len(field.elements) or (len(values) > len(field.elements) and not has_positional):
                raise ValueError(f"{g.spelling} takes {len(field.elements)} values, got {len(values)}"
                                 + (f": {' '.join(values)}" if values else ""))
        for k, value in enumerate(values):
            element = field.elements[min(k, len(field.elements) - 1)] if field.kind == "fixed" else field.elements[0]
            why = _bad_value(value, element, field.none)
            if why:
                raise ValueError(f"{g.spelling} {why}")


# ------------------------------------------------------------------------------------------ tyro, one line
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def one_line(text: str) -> str:
    """tyro's boxed error as one line: the box's first section (what went wrong), without its title, borders,
    colours and help footer. tyro draws the box with line characters, or in plain ASCII where the output cannot
    take them (the title then a line of its own)."""
    sections: list[list[str]] = [[]]
    titled = False
    for line in _ANSI.sub("", text).splitlines():
        line = line.strip()
        if line[:1] in ("╭", "╰"):
            titled = titled or line[:1] == "╭"
            continue
        line = line.strip("│").strip()
        if line and set(line) <= set("─━-"):
            sections.append([])
        elif line:
            sections[-1].append(line)
    sections = [s for s in sections if s]
    if not titled and len(sections) > 1:
        sections = sections[1:]
    body = [line for line in (sections[0] if sections else []) if not line.startswith("For full helptext")]
    return " ".join(body) or "the command line was not understood"


def tyro_one_line(call: Callable[[], T], prog: str | None = None) -> T:
    """``call()`` (a ``tyro.cli``) with what tyro refuses as one ``error:`` line, exit status 2; its help and
    anything it writes on success pass through unchanged."""
    caught = io.StringIO()
    code: Any = None
    try:
        with contextlib.redirect_stderr(caught):
            return call()
    except SystemExit as e:
        code = e.code
        if code in (0, None):
            raise
    finally:
        if code in (0, None):
            sys.stderr.write(caught.getvalue())
    fail(one_line(caught.getvalue()) + (f" ({prog} --help lists the flags)" if prog else ""))


def cli(cls: type[T], argv: Sequence[str] | None = None, *, prog: str | None = None, **tyro_kwargs: Any) -> T:
    """``tyro.cli(cls)`` whose every refusal is one line naming the flag (:func:`check_argv`, then tyro's own
    answer folded into one line), exit status 2."""
    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        check_argv(cls, argv, prog)
    except ValueError as e:
        fail(str(e))
    return tyro_one_line(lambda: tyro.cli(cls, args=argv, prog=prog, **tyro_kwargs), prog)
