"""Settings declared once: a dataclass's fields are the command line's options.

Each field gives its option's name (``--field-name``, or ``metadata={"flag": ...}``), default (the field's), type
(the default's; a bool is a ``--x/--no-x`` switch) and help (the field's doc: the ``#:`` comment above it, or the
comment after it). Nested settings take a prefix for their help.

    add_options(parser, GroundSettings(), ["max_wait_s", "mapping"])
    settings = from_options(GroundSettings(), args, ["max_wait_s", "mapping"])
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
from functools import lru_cache

from pomar.cli import InputError

_FIELD = re.compile(r"^(\s+)(\w+)\s*:\s*[^=#]+?(?:=\s*(.*?))?\s*(?:#\s*(.*))?$")


@lru_cache(maxsize=None)
def field_docs(cls) -> dict[str, str]:
    """Each field's doc, read from the class's source: the ``#:`` lines above the field, else its trailing comment."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    docs, pending, indent = {}, [], None
    for line in lines[1:]:
        s = line.strip()
        if s.startswith("#:"):
            pending.append(s[2:].strip())
            continue
        m = _FIELD.match(line)
        if m and (indent is None or len(m.group(1)) == indent) and not s.startswith(("def ", "@", "class ")):
            indent = len(m.group(1))
            doc = " ".join(pending) or (m.group(4) or "")
            docs[m.group(2)] = doc.strip()
        if not s.startswith("#"):
            pending = []
    return docs


def one_line(doc: str) -> str:
    """A doc's first sentence, as an option's help (argparse's % escaped)."""
    first = re.split(r"(?<=[a-z0-9)\]])\. ", doc, maxsplit=1)[0].rstrip(".")
    return first.replace("%", "%%")


def flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag", "--" + f.name.replace("_", "-"))


def add_options(parser, settings, names: list[str], prefix: str = "") -> None:
    """Options for these fields of a settings dataclass instance (its values are the defaults)."""
    fields = {f.name: f for f in dataclasses.fields(settings)}
    docs = field_docs(type(settings))
    for name in names:
        f = fields[name]
        default = getattr(settings, name)
        doc = one_line(docs.get(name, ""))
        kw = {"dest": f.metadata.get("dest", name), "default": default,
              "help": prefix + doc + ("" if default is None or default == [] else ("; " if doc else "") + "default %(default)s")}
        for key in ("choices", "nargs", "metavar", "action", "required"):  # argparse's own, where a field needs them
            if key in f.metadata:
                kw[key] = f.metadata[key]
        if isinstance(default, bool):
            parser.add_argument(flag(f), action=argparse.BooleanOptionalAction, **kw)
        else:
            kind = f.metadata.get("type") or (type(default) if default is not None else str)
            parser.add_argument(flag(f), type=kind, **kw)


class SettingsError(InputError, ValueError):
    """Options that do not fit together (a settings class's own check refused them)."""


def from_options(settings, args, names: list[str]):
    """A copy of the settings with these fields from parsed options; SettingsError where they do not fit."""
    fields = {f.name: f for f in dataclasses.fields(settings)}
    try:
        return dataclasses.replace(settings, **{n: getattr(args, fields[n].metadata.get("dest", n)) for n in names})
    except ValueError as exc:
        raise SettingsError(str(exc)) from None
