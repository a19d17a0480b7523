"""Prometheus ``/metrics``: queue figures read from the database at scrape time (so every API replica
reports the same numbers, whichever process did the work)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from common.job_state import JobState
from common.queue import JobQueue

WAIT_BUCKETS = (0.1, 0.5, 1, 5, 15, 60, 300, 900, 3600)
RUN_BUCKETS = (1, 5, 15, 60, 300, 900, 1800, 3600, 7200)


def _histogram(name: str, doc: str, values: Iterable[float], bounds: tuple[float, ...]) -> HistogramMetricFamily:
    values = list(values)
    buckets: list[tuple[str, float]] = [(str(b), float(sum(1 for v in values if v <= b))) for b in bounds]
    buckets.append(("+Inf", float(len(values))))
    return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=sum(values))


class QueueCollector(Collector):
    def __init__(self, queue: JobQueue) -> None:
        self.queue = queue

    def collect(self) -> Iterator[Metric]:
        stats = self.queue.stats()
        jobs = GaugeMetricFamily("hoi_refine_jobs", "Jobs per state", labels=["state"])
        for state in JobState:
            jobs.add_metric([state.value], stats.jobs_by_state.get(state, 0))
        yield jobs
        yield CounterMetricFamily("hoi_refine_claims", "Jobs claimed by workers (all attempts)", stats.claims_total)
        yield _histogram(
            "hoi_refine_queue_wait_seconds", "Time from (re)queue to claim, recent jobs",
            stats.queue_wait_seconds, WAIT_BUCKETS,
        )  # fmt: skip
        yield _histogram(
            "hoi_refine_run_seconds", "Time from claim to finish, recent jobs", stats.run_seconds, RUN_BUCKETS
        )


def make_registry(queue: JobQueue) -> CollectorRegistry:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(QueueCollector(queue))
    return registry


def render(registry: Any) -> bytes:
    return generate_latest(registry)
