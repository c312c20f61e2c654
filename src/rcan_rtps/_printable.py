"""Text from outside, made safe to print: to a log line or to a terminal."""

from __future__ import annotations


def shown(text: str) -> str:
    """`text` with every character that does not print (ESC, BEL, CR, a newline, the 8-bit
    CSI, a bidi override) written as its escape (`\\x1b`, `\\u202e`); anything printable,
    non-ASCII letters too, as it is. What a client, a network peer or a DDS participant names
    is shown, never obeyed: a newline would forge a log line, an escape sequence retitle the
    operator's terminal or hide lines of a listing."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii")
                   for c in text)
