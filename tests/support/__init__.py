"""Shared test material (builders, fixtures, harnesses); no tests live here.

* ``queue_fixtures`` — a database per test on SQLite and PostgreSQL, tiny sequences, fake results, ``ApiHarness``
  (registered for every test package as a pytest plugin in tests/conftest.py);
* ``queue_claimer`` — a process that claims jobs, for the concurrency tests;
* ``api`` — request bodies for the API tests;
* ``synthetic_push`` — a push whose object motion is what a known hand motion does in simulation;
* ``mano`` — a MANO-format test model (``mano_dir`` fixture) and a MANO hand sequence;
* ``dexycb_tree`` — a tiny DexYCB release tree.
"""
