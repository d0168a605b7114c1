"""What every command line of the project (``python -m sim``, ``onboard``, ``ground``, ``pomar``, ``export``) does
with bad input and with Ctrl-C, written once: an :class:`InputError` is one line on stderr, exit 2, never a traceback;
Ctrl-C (or SIGTERM, see :mod:`pomar.shutdown`) before a command sets its own handling is "interrupted", exit 130."""

from __future__ import annotations

import logging
import os
import sys


class InputError(Exception):
    """Input a user can fix (a file missing, malformed or of another flight; an option that does not fit): its
    message names the file and what is wrong. Each reader's own error class derives from it."""


def read_json(path, error=InputError):
    """A JSON file's content; ``error`` (an InputError class) naming the file where it cannot be read or is not
    JSON."""
    import json
    from pathlib import Path

    path = Path(path)
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise error(f"{path}: cannot be read ({e.strerror or e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        why = f"{e.msg}, line {e.lineno}" if isinstance(e, json.JSONDecodeError) else "not text"
        raise error(f"{path}: not JSON ({why})") from None


def run(command, args) -> int:
    """``command(args)``'s exit code; an InputError, or a file the system refuses (OSError: missing, unreadable, a
    full disk; it names the file), is one line on stderr and exit 2."""
    try:
        return command(args)
    except (InputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def exit_with(main, hard: bool = False):
    """Exit with ``main()``'s code; Ctrl-C is "interrupted", exit 130. ``hard``: once the logs and streams are
    flushed, skip the interpreter's teardown (a command that has written and closed all it writes)."""
    try:
        code = main()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        code = 130
    except InputError as exc:  # raised while the arguments were checked, before a command ran
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    if hard:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(int(code or 0))
    sys.exit(code)
