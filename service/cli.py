"""``hoi-refine serve`` (the REST service under uvicorn) and ``hoi-refine keys`` (API keys).

``serve`` waits for the database with backoff, upgrades it to the migration head, then runs uvicorn; the
same database URL (``HOI_REFINE_DATABASE_URL`` or the SQLite file under ``HOI_REFINE_VAR_DIR``) serves the
workers. Heavy imports stay inside the handlers so ``hoi-refine --help`` is fast.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from common.api_key_store import ApiKeyStore


def register_serve(subparsers: Any) -> None:
    serve = subparsers.add_parser(
        "serve",
        help="run the REST API (waits for the database and upgrades it to the latest migration first)",
        description="Run the /v1 jobs API with uvicorn. The database comes from HOI_REFINE_DATABASE_URL "
        "(PostgreSQL) or a SQLite file under HOI_REFINE_VAR_DIR.",
    )
    serve.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    serve.add_argument(
        "--fd",
        type=int,
        help="serve on the already-bound, listening socket inherited as this file descriptor instead of binding "
        "--host/--port (which then only name it); `hoi-refine up` starts the API this way",
    )
    serve.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (default 1)")
    serve.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    serve.add_argument("--no-migrate", action="store_true", help="do not upgrade the database at start-up")
    serve.set_defaults(func=_cmd_serve)


def register_keys(subparsers: Any) -> None:
    keys = subparsers.add_parser("keys", help="manage API keys", description="Create, list and revoke API keys.")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    create = keys_sub.add_parser("create", help="create a key and print it (shown once; only a hash is stored)")
    create.add_argument("name", help="who the key is for")
    create.set_defaults(func=_cmd_keys_create)
    listing = keys_sub.add_parser("list", help="list keys (names, prefixes, creation times, revocations)")
    listing.set_defaults(func=_cmd_keys_list)
    revoke = keys_sub.add_parser(
        "revoke",
        help="revoke a key: every request with it gets 401 from then on",
        description="Revoke the one key named by its name, its id, the start of its prefix as 'keys list' shows "
        "it (at least 6 characters, e.g. hoi_ab), or the whole key. A running server may accept the key for a "
        "few more seconds (its lookup cache). Exit status 2 when nothing or more than one key matches.",
    )
    revoke.add_argument("name_or_prefix", metavar="NAME_OR_PREFIX", help="the key's name, prefix, id, or the key")
    revoke.add_argument(
        "--cancel-jobs",
        action="store_true",
        help="also cancel the key's QUEUED jobs and ask its RUNNING ones to stop (otherwise they still run, "
        "and nobody can read their results: the key that owns them no longer works)",
    )
    revoke.set_defaults(func=_cmd_keys_revoke)


def prepare_database(url: str, wait_seconds: float, migrate: bool = True) -> None:
    """Wait for the database (exponential backoff) and upgrade it to head."""
    from common.database import create_engine_for, upgrade_to_head, wait_for_database

    engine = create_engine_for(url)
    try:
        wait_for_database(engine, timeout_s=wait_seconds)
    finally:
        engine.dispose()
    if migrate:
        upgrade_to_head(url)


def _cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from common.settings import get_settings

    settings = get_settings()
    url = settings.resolved_database_url()
    prepare_database(url, settings.database_wait_seconds, migrate=not args.no_migrate)
    uvicorn.run(
        "service.app:create_app",
        factory=True,
        host=args.host,
        port=args.port,
        fd=args.fd,
        workers=args.workers,
        log_level=args.log_level,
    )
    return 0


@contextmanager
def _key_store() -> Iterator[ApiKeyStore]:
    """The ``ApiKeyStore`` of the configured database (migrated to head first); its engine is closed after."""
    from common.api_key_store import ApiKeyStore
    from common.database import create_engine_for
    from common.settings import get_settings

    settings = get_settings()
    prepare_database(settings.resolved_database_url(), settings.database_wait_seconds)
    engine = create_engine_for(settings.resolved_database_url())
    try:
        yield ApiKeyStore(engine)
    finally:
        engine.dispose()


def _cmd_keys_create(args: argparse.Namespace) -> int:
    with _key_store() as store:
        key_id, plaintext = store.create(args.name)
    print(plaintext)
    print(f"created API key {key_id} for {args.name!r}; it is shown only this once", file=sys.stderr)
    return 0


def _cmd_keys_list(_args: argparse.Namespace) -> int:
    with _key_store() as store:
        rows = store.list()
    for key in rows:
        revoked = f"  REVOKED {key.revoked_at:%Y-%m-%d %H:%M:%S}" if key.revoked_at else ""
        print(f"{key.id}  {key.prefix}...  {key.created_at:%Y-%m-%d %H:%M:%S}  {key.name}{revoked}")
    return 0


def _cmd_keys_revoke(args: argparse.Namespace) -> int:
    # No match or several matches raise a project error: ``hoi-refine`` prints it and exits 2.
    with _key_store() as store:
        key, newly = store.revoke(args.name_or_prefix)
        cancelled = None
        if args.cancel_jobs:
            from common.queue import JobQueue

            cancelled = JobQueue(store.engine).cancel_jobs_of_key(key.id)
    assert key.revoked_at is not None
    when = f"{key.revoked_at:%Y-%m-%d %H:%M:%S} UTC"
    state = "revoked" if newly else f"was already revoked (at {when})"
    print(f"API key {key.id} ({key.prefix}..., {key.name!r}) {state}")
    if cancelled is not None:
        print(f"its jobs: {cancelled[0]} queued cancelled, {cancelled[1]} running asked to stop")
    return 0
