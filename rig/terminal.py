"""Text from configuration files, recordings and the command line, made safe to echo on
a terminal: the one helper every ``rig`` message that repeats user text goes through.

A configuration key may hold a newline and ``ESC [2J`` (which clears the screen), a
file name a carriage return, a recording's metadata a 7 MB string.  :func:`safe` escapes
every control character (C0, DEL, C1, Unicode line and paragraph separators and the
invisible format characters, bidirectional overrides included) as ``\\xNN`` /
``\\uNNNN`` and cuts the text at :data:`MAX_ECHO_CHARS` characters, saying how much was
cut.  :func:`refuse` prints a command's one-line refusal with it.
"""

from __future__ import annotations

import re
import sys

__all__ = ["MAX_ECHO_CHARS", "refuse", "safe"]

#: longest text echoed in one message (a refusal names a key, a value, a path and what
#: is allowed: a few hundred characters)
MAX_ECHO_CHARS = 1000

_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200b-\u200f\u2028-\u202e\u2060-\u206f"
                     "\ufeff\ufff9-\ufffb]")


def _escape(m: re.Match[str]) -> str:
    c = ord(m.group())
    return {10: "\\n", 13: "\\r", 9: "\\t"}.get(c) or (
        f"\\x{c:02x}" if c < 0x100 else f"\\u{c:04x}")


def safe(text: object, limit: int = MAX_ECHO_CHARS) -> str:
    """``str(text)`` with control characters escaped, at most about ``limit`` characters
    (a longer text ends in ``... [N more characters]``)."""
    s = str(text)
    head = _UNSAFE.sub(_escape, s[:limit])
    if len(head) > limit:          # escapes lengthened it
        head = head[:limit]
    rest = len(s) - limit
    return head if rest <= 0 else f"{head}... [{rest} more characters]"


def refuse(command: str, message: object) -> None:
    """Print ``rig COMMAND: MESSAGE`` (made :func:`safe`) as one line on stderr."""
    print(f"rig {command}: {safe(message)}", file=sys.stderr)
