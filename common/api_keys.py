"""API keys: high-entropy bearer tokens stored only as SHA-256 hashes (DESIGN §2, issue #4 item 4).

A key has 256 random bits, so a plain (unsalted) SHA-256 is enough: there is no dictionary to attack,
and the hash can be looked up by equality with an index. The plaintext is shown once, at creation.
"""

from __future__ import annotations

import hashlib
import secrets

from common.errors import AuthenticationError

KEY_PREFIX = "hoi_"


def new_key() -> str:
    return KEY_PREFIX + secrets.token_urlsafe(32)


def hash_key(plaintext: str) -> str:
    return hashlib.sha256(plaintext.encode()).hexdigest()


def display_prefix(plaintext: str) -> str:
    """The first characters, for telling keys apart in listings (not enough to guess the rest)."""
    return plaintext[: len(KEY_PREFIX) + 6]


def require_key(key_id: str | None) -> str:
    if key_id is None:
        raise AuthenticationError("invalid or revoked API key")
    return key_id
