"""Routers of the REST service: ``jobs`` (``/v1/jobs``) and ``ops`` (health, readiness, metrics)."""
