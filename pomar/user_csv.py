"""A CSV file the user writes (an orchard layout, hand counts): its lines as records, each with its line number, so
that a reader names the line it refuses; a file missing, unreadable, not text or without the columns it needs is one
line naming the file."""

from __future__ import annotations

import csv
from pathlib import Path


def user_csv(path: Path, columns: list[str], error: type, what: str) -> list[tuple[int, dict]]:
    """(line number, record) of each line of ``path``; ``error`` (an InputError) where it does not read or lacks a
    column of ``columns`` (``what``: the file's kind, as the message names it)."""
    try:
        with open(path, newline="") as f:
            rd = csv.DictReader(f)
            missing = [c for c in columns if c not in (rd.fieldnames or [])]
            if missing:
                raise error(f"{path}:1: {what} needs the columns {','.join(columns)} (missing: {', '.join(missing)})")
            return [(rd.line_num, d) for d in rd]
    except OSError as e:
        raise error(f"{path}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text (CSV) file") from None
