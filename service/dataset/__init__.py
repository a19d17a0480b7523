"""A dataset release (issue #54 item 4): ``hoi-refine dataset export`` from a batch (through the API) or a folder
of results.

Modules:

* ``sources``   where results come from: a folder of ``*.result.npz``, or a batch's jobs through the API;
* ``datasheet`` the release's ``README.md`` and its plots;
* ``export``    writes a release: result files, both Parquet tables, plots, datasheet, ``SHA256SUMS``;
* ``cli``       the command.

The release's format (layout, the two tables' columns with units, one result's rows) is
``common.release_format`` and ``common.release_tables``, shared with ``hoi-refine verify``, which checks a release;
its checksums are ``common.release_manifest``. Client-side like ``service.submit``: it talks to the API through
``common.api_client`` and reads results with ``common.result_format``; nothing here imports the worker.
"""
