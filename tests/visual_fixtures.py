"""A short real refinement result for the visual tests (issue #18), made once per test session.

The 24-frame built-in grasp-and-lift refined with the default budget and no restarts (about 10 s on 2 loaded
cores): the raw replay drops the box, the refined hand lifts it 20 cm, so a video must show the box rise.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from common.job_options import JobOptions

#: Set to 1 to let tests rewrite the pictures under docs/ (never in CI: it would dirty the tree).
UPDATE_DOCS_ENV = "HOI_REFINE_UPDATE_DOCS"
DOCS = Path(__file__).resolve().parent.parent / "docs"


def update_docs() -> bool:
    return os.environ.get(UPDATE_DOCS_ENV) == "1"


@pytest.fixture(scope="session")
def short_refine_result() -> bytes:
    from worker.example import short_example_sequence
    from worker.refine.run import refine_sequence

    outcome = refine_sequence(short_example_sequence(), JobOptions(restarts=0))
    return outcome.to_npz_bytes()
