"""The assertion the forgery tests share: a result fails ``verify`` naming every given field."""

from __future__ import annotations

import pytest

from common.errors import ResultMismatchError
from worker.verification import verify_result


def fails_naming(blob: bytes, *fields: str) -> str:
    """``verify_result(blob)`` raises, and its message names each of ``fields``; returns the message."""
    with pytest.raises(ResultMismatchError) as info:
        verify_result(blob)
    text = str(info.value)
    for name in fields:
        assert name in text, text
    return text
