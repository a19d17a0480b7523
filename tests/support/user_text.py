"""What user-facing text (``--help``, the API description, error answers) must not hold: references to the design
document or to the project's source files and modules, which a user of the installed tool does not have."""

from __future__ import annotations

import re

#: ``DESIGN``, a module path (``common.job_options``, ``worker/refine/...``), or a Python file name.
SOURCE_REFERENCE = re.compile(
    r"DESIGN|\b(?:common|service|worker|bench|tests|migrations)[./][A-Za-z_]+|\b[\w/.-]+\.py\b"
)
#: Python files a user does get: the plain-MuJoCo export's own script.
ALLOWED = frozenset({"replay.py"})


def source_references(text: str) -> list[str]:
    """Each reference in ``text``, with some context."""
    return [
        text[max(0, m.start() - 60) : m.end() + 20].replace("\n", " ")
        for m in SOURCE_REFERENCE.finditer(text)
        if m.group(0).rsplit("/", 1)[-1].strip("`") not in ALLOWED
    ]
