"""``hoi-refine submit``: send a whole dataset to a hoi-refine service, resumably (issue #6, item 1).

``discovery`` finds and loads the sequences, ``payload`` packs each into a reproducible upload and derives its
Idempotency-Key, ``manifest`` records progress in ``<out>/manifest.json``, ``common.api_client`` talks to the REST
API with retries, ``runner`` drives it all (``run_submit``), ``report`` draws progress and the summary, and
``cli`` registers the subcommand. Client-side only: nothing here imports FastAPI, the database or MuJoCo.
"""
