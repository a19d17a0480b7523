"""Standard Webhooks signatures (https://www.standardwebhooks.com, the ``standardwebhooks`` package).

Each delivery carries ``webhook-id`` (the same on every retry, so a receiver can drop duplicates),
``webhook-timestamp`` (Unix seconds; receivers reject stale ones, which stops replays) and
``webhook-signature: v1,<base64 HMAC-SHA256 over "{id}.{timestamp}.{body}">`` keyed with the secret's bytes.
A receiver verifies with ``standardwebhooks.Webhook(secret).verify(body, headers)``.
"""

from __future__ import annotations

import base64
import json
import secrets
from datetime import datetime
from typing import Any

from standardwebhooks.webhooks import Webhook

SECRET_PREFIX = "whsec_"


def new_secret() -> str:
    """A fresh signing secret: ``whsec_`` + 32 random bytes in base64 (the scheme's format)."""
    return SECRET_PREFIX + base64.b64encode(secrets.token_bytes(32)).decode()


def body_of(payload: dict[str, Any]) -> str:
    """The exact bytes that are signed and sent (compact JSON, keys sorted so a retry sends the same body)."""
    return json.dumps(payload, separators=(",", ":"), sort_keys=True)


def signed_headers(secret: str, msg_id: str, when: datetime, body: str) -> dict[str, str]:
    return {
        "webhook-id": msg_id,
        "webhook-timestamp": str(int(when.timestamp())),
        "webhook-signature": Webhook(secret).sign(msg_id, when, body),
        "content-type": "application/json",
    }
