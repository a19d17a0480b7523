"""The API schema states ``text_problem``'s rule as a pattern (common/safe_text.py): the two agree on any text."""

from __future__ import annotations

import re

from hypothesis import given, settings
from hypothesis import strategies as st

from common.safe_text import BIDI_CONTROLS, FREE_TEXT_PATTERN, TEXT_PATTERN, text_problem


def compiled(pattern: str) -> re.Pattern[str]:
    # JSON-schema (ECMA) '$' is the end of the text; Python's also matches before a final newline.
    assert pattern.endswith("$")
    return re.compile(pattern[:-1] + r"\Z")


NAMES, FREE = compiled(TEXT_PATTERN), compiled(FREE_TEXT_PATTERN)
#: Text that is mostly ordinary, with control, bidi and whitespace characters mixed in.
TEXT = st.text(st.one_of(st.characters(), st.sampled_from([*sorted(BIDI_CONTROLS), "\t", "\n", "\r", "\x85"])))


@settings(max_examples=500, deadline=None)
@given(TEXT)
def test_the_schema_patterns_say_what_text_problem_refuses(text: str) -> None:
    assert bool(NAMES.search(text)) == (text_problem(text, 10**6) is None)
    assert bool(FREE.search(text)) == (text_problem(text, 10**6, allow_whitespace_controls=True) is None)


def test_the_patterns_on_examples() -> None:
    assert NAMES.search("Cracker box é 漢") and FREE.search("line one\nline two\tend\r\n")
    for bad in ("a\x00", "tab\there", "new\nline", "\u202eevil", "c1\x85"):
        assert not NAMES.search(bad), bad
    assert not FREE.search("\u2066x") and not FREE.search("bell\x07")
