"""Which strings from a client we store and show back (issue #16, point 6).

Decision: sequence names, object names and ``meta`` keys and values are **rejected** (422 naming the
field and the code point) when they hold

* NUL (U+0000): PostgreSQL cannot store it in text or JSONB, so SQLite and PostgreSQL would disagree;
* any other control character (Unicode category Cc: C0, DEL, C1), tab and newline included for names;
* a bidirectional formatting character (U+061C, U+200E/F, U+202A-U+202E, U+2066-U+2069), which can make
  a name shown in a terminal or a web page read differently from what is stored ("Trojan source").

Rejecting rather than escaping keeps what is stored equal to what was sent (no lossy rewrite the client
does not know about). Error messages that quote client text use ``shown()``: ``repr`` (which escapes
control and bidi characters) cut to a short length.
"""

from __future__ import annotations

import unicodedata

from common.errors import FieldProblem

BIDI_CONTROLS = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")
#: ``meta`` values may hold tabs and line breaks (free text); names may not.
TEXT_WHITESPACE = frozenset("\t\n\r")
MAX_META_ENTRIES = 64


def _refused_class(allow_whitespace_controls: bool) -> str:
    """A regular-expression character class of what ``text_problem`` refuses: category Cc (U+0000-U+001F,
    U+007F-U+009F) and the bidi controls, less tab and line breaks for free text."""
    points = sorted({*range(0x20), *range(0x7F, 0xA0), *map(ord, BIDI_CONTROLS)})
    if allow_whitespace_controls:
        points = [p for p in points if chr(p) not in TEXT_WHITESPACE]
    runs: list[list[int]] = []
    for p in points:
        if runs and p == runs[-1][1] + 1:
            runs[-1][1] = p
        else:
            runs.append([p, p])
    return "".join(f"\\u{a:04x}" + (f"-\\u{b:04x}" if b > a else "") for a, b in runs)


#: ``text_problem``'s rule as a JSON-schema pattern (the API schema states it; the server checks it itself, with
#: messages naming the code point): names, meta keys, and meta values (``FREE_TEXT_PATTERN``).
TEXT_PATTERN = f"^[^{_refused_class(False)}]*$"
FREE_TEXT_PATTERN = f"^[^{_refused_class(True)}]*$"
MAX_META_KEY_CHARS = 100
MAX_META_VALUE_CHARS = 2000


def text_problem(value: object, max_chars: int, allow_whitespace_controls: bool = False) -> str | None:
    """Why ``value`` may not be stored as a name / meta string, or None when it may."""
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if len(value) > max_chars:
        return f"must be at most {max_chars} characters, got {len(value)}"
    for index, char in enumerate(value):
        if char == "\x00":
            return f"must not contain NUL (U+0000), found at index {index}"
        if allow_whitespace_controls and char in TEXT_WHITESPACE:
            continue
        if unicodedata.category(char) == "Cc":
            return f"must not contain control characters, found U+{ord(char):04X} at index {index}"
        if char in BIDI_CONTROLS:
            return f"must not contain bidirectional formatting characters, found U+{ord(char):04X} at index {index}"
    return None


def shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` (control and bidi characters escaped), cut to ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def meta_problems(meta: object) -> list[FieldProblem]:
    """A sequence's ``meta``: at most ``MAX_META_ENTRIES`` string keys and values, each passing ``text_problem``."""
    if not isinstance(meta, dict):
        return [FieldProblem("meta", f"must be an object of strings, got {type(meta).__name__}")]
    if len(meta) > MAX_META_ENTRIES:
        return [FieldProblem("meta", f"may hold at most {MAX_META_ENTRIES} entries, got {len(meta)}")]
    problems = []
    for key, value in meta.items():
        if (why := text_problem(key, MAX_META_KEY_CHARS)) is not None:
            problems.append(FieldProblem("meta", f"key {shown(key)} {why}"))
        elif (why := text_problem(value, MAX_META_VALUE_CHARS, allow_whitespace_controls=True)) is not None:
            problems.append(FieldProblem(f"meta.{key}", why))
    return problems
