"""A dataset release (issue #54 item 4): ``hoi-refine dataset export`` from a batch (through the API) or a folder
of results.

Modules:

* ``columns``   the release's layout and its two tables' columns (name, type, unit, meaning): one definition the
                writer, the datasheet and the docs share;
* ``sources``   where results come from: a folder of ``*.result.npz``, or a batch's jobs through the API;
* ``tables``    one result's index row and contact rows;
* ``datasheet`` the release's ``README.md`` and its plots;
* ``export``    writes a release: result files, both Parquet tables, plots, datasheet, ``SHA256SUMS``;
* ``cli``       the command.

Client-side like ``service.submit``: it talks to the API through ``common.api_client`` and reads results with
``common.result_format``; nothing here imports the worker.
"""
