"""What every `magstation` command module shares: the one-line user-facing error and text made
safe for a terminal.  (Its own module: ``python -m groundstation.cli`` runs cli.py as
``__main__``, so a class defined there would not be the one the other command modules raise.)"""
from __future__ import annotations

import re

__all__ = ["CliError", "printable"]


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code 1."""


# control characters (C0, DEL, C1), bidi/zero-width controls, lone surrogates (undecodable file names)
_UNPRINTABLE = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2066-\u2069\ud800-\udfff]")


def printable(text: object, *, lines: bool = False) -> str:
    """``text`` safe for a terminal: control characters from files (escape sequences, BEL,
    bidi overrides) shown as \\xNN / \\uNNNN instead of acted on; newlines kept only when ``lines``."""
    def escape(found: re.Match) -> str:
        c = found.group()
        return f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}"
    text = _UNPRINTABLE.sub(escape, str(text))
    return text if lines else text.replace("\n", "\\n").replace("\t", " ")
