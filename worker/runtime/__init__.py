"""The worker runtime: heartbeat, worker loop, Ray actors and pool, ``hoi-refine up``, the demo client."""
