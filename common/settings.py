"""Settings from ``HOI_REFINE_*`` environment variables (pydantic-settings).

``get_settings()`` is cached so every module sees one object; tests call ``get_settings.cache_clear()``
after changing the environment.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

if TYPE_CHECKING:
    from common.sequence_npz import ParseLimits


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="HOI_REFINE_", extra="ignore")

    # --- storage -------------------------------------------------------------------------------
    #: SQLAlchemy URL. Unset: a SQLite file under ``var_dir``. PostgreSQL: ``postgresql+psycopg://...``.
    database_url: str | None = None
    #: Working directory for the SQLite file, caches and local results.
    var_dir: Path = Path("var")
    #: Convex-decomposition cache (content-hashed); defaults to ``var_dir/cache``.
    cache_dir: Path | None = None

    # --- data ----------------------------------------------------------------------------------
    #: Folder with YCB meshes + objects.json for DexYCB-style NPZ files that name their object.
    ycb_dir: Path | None = None
    #: Folder with MANO_RIGHT.pkl / MANO_LEFT.pkl (optional; licensed, never shipped).
    mano_dir: Path | None = None
    #: Folder the shipped robot hands' models are read from (``--hand allegro|leap``): a checkout of the public
    #: dex-urdf repository (``robots/hands/...``). Never shipped.
    robot_dir: Path | None = None
    #: Sequences longer than this are rejected at validation.
    max_frames: int = Field(default=3000, gt=0)

    #: Largest object mesh a sequence may carry (vertices / triangles).
    max_mesh_vertices: int = Field(default=200_000, gt=0)
    max_mesh_faces: int = Field(default=400_000, gt=0)
    #: An uploaded NPZ's members may add up to this many bytes uncompressed (checked before decompressing).
    max_sequence_bytes: int = Field(default=64 * 1024 * 1024, gt=0)

    # --- service -------------------------------------------------------------------------------
    #: Request bodies are counted as they arrive (any transfer encoding): 413 beyond this.
    max_request_bytes: int = Field(default=64 * 1024 * 1024, gt=0)
    #: JSON submissions are parsed into Python objects (tens of bytes per number), so they get a smaller
    #: limit than NPZ uploads; large sequences go as NPZ (multipart).
    max_json_request_bytes: int = Field(default=16 * 1024 * 1024, gt=0)
    max_active_jobs_per_key: int = Field(default=100, gt=0)
    #: Seconds a worker's lease lasts without a heartbeat.
    lease_seconds: float = Field(default=30.0, gt=0)
    #: Attempts before a job whose leases keep expiring is FAILED.
    max_attempts: int = Field(default=3, gt=0)
    #: Base of the exponential backoff before a requeued job may be claimed again.
    retry_backoff_seconds: float = Field(default=2.0, ge=0)
    #: Retry-After (s) sent with 429 when a key has ``max_active_jobs_per_key`` jobs queued or running.
    active_jobs_retry_after_seconds: int = Field(default=30, gt=0)
    #: Retry-After (s) sent with the status of a job that is not finished (client polling interval).
    poll_retry_after_seconds: int = Field(default=2, gt=0)
    #: How long ``hoi-refine serve`` waits for the database at start-up.
    database_wait_seconds: float = Field(default=60.0, gt=0)
    #: Seconds between the reads of a server-sent event stream (``/v1/jobs/{id}/events`` etc.).
    events_poll_seconds: float = Field(default=1.0, gt=0)
    #: Seconds between keep-alive comments on an idle event stream (proxies close silent connections).
    events_heartbeat_seconds: float = Field(default=15.0, gt=0)
    #: Longest life of one event stream; the client reconnects with Last-Event-ID and loses nothing.
    events_max_seconds: float = Field(default=900.0, gt=0)

    # --- webhooks (sent by a background task of the API process; never by a worker) ----------
    #: Seconds between the dispatcher's looks for new events and due deliveries.
    webhook_poll_seconds: float = Field(default=1.0, gt=0)
    #: Deadline of one delivery: resolving the host, connecting, sending and reading the answer, all together.
    webhook_timeout_seconds: float = Field(default=5.0, gt=0)
    #: Connect timeout within that deadline.
    webhook_connect_timeout_seconds: float = Field(default=3.0, gt=0)
    #: Bytes of a receiver's answer read at most (the status alone decides; the rest is never read).
    webhook_max_response_bytes: int = Field(default=64 * 1024, ge=0)
    #: Host names and address ranges that webhooks may target although they are not public, comma-separated
    #: (e.g. ``hooks.internal,10.8.0.0/16,127.0.0.1``); empty: public addresses only (``common.webhook_targets``).
    webhook_allow_targets: str = ""
    #: CA certificates (PEM file) that https webhook receivers' certificates are verified against instead of the
    #: public ones (certifi): for receivers with certificates from an internal CA.
    webhook_ca_file: Path | None = None
    #: Attempts before a delivery is given up (FAILED in the delivery log).
    webhook_max_attempts: int = Field(default=8, gt=0)
    #: Base of the exponential backoff between attempts (doubling, capped at one hour).
    webhook_backoff_seconds: float = Field(default=5.0, ge=0)
    #: Run the dispatcher in this API process (off when a separate process sends the webhooks).
    webhook_dispatcher: bool = True

    # --- workers -------------------------------------------------------------------------------
    #: Niceness added to worker processes (0-19): the physics yields the CPU to the API's status polls.
    worker_nice: int = Field(default=10, ge=0, le=19)
    #: Niceness a worker of more than one thread adds to the thread that draws a job's preview beside the next
    #: job's computation (0-19): the preview fills the rollouts' barrier waits instead of slowing them.
    preview_nice: int = Field(default=5, ge=0, le=19)

    @field_validator("webhook_allow_targets")
    @classmethod
    def _allow_list_parses(cls, value: str) -> str:
        from common.webhook_targets import parse_allow_list  # local: this module stays free of project imports

        parse_allow_list(value)  # a typo fails at start-up, naming the entry
        return value

    def parse_limits(self) -> ParseLimits:
        """What one uploaded sequence may hold (frames, mesh size, uncompressed bytes)."""
        from common.npz_safe import NpzLimits  # local: settings stay importable without NumPy
        from common.sequence_npz import ParseLimits

        npz = NpzLimits(max_member_bytes=self.max_sequence_bytes, max_total_bytes=self.max_sequence_bytes)
        return ParseLimits(self.max_frames, self.max_mesh_vertices, self.max_mesh_faces, npz)

    def resolved_cache_dir(self) -> Path:
        return self.cache_dir if self.cache_dir is not None else self.var_dir / "cache"

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.var_dir / 'hoi-refine.sqlite3').resolve()}"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    return Settings()
