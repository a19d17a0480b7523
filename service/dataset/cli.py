"""``hoi-refine dataset export --out DIR (--from FOLDER | --batch ID --api URL --key KEY) [--title TEXT]``.

``--api`` and ``--key`` default to ``HOI_REFINE_API_URL`` / ``HOI_REFINE_API_KEY``, as for ``submit``. Heavy imports
stay inside the handler so ``hoi-refine --help`` stays fast."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from common.errors import ConfigurationError


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("dataset", help="a dataset release from a batch or a folder of results",
                              description="Dataset releases (issue #54).")
    sub = p.add_subparsers(dest="dataset_command", required=True, metavar="ACTION")
    e = sub.add_parser(
        "export",
        help="write a release: result files, contacts and index as Parquet, datasheet, checksums",
        description="Write a dataset release into OUT: each sequence's result file (results/), the contacts of "
        "all sequences as one Parquet table (contacts.parquet: sequence, frame, hand, body, part, world and "
        "object-frame points, normal, force, torque, depth), an index with one row per sequence (index.parquet: "
        "outcome and reasons, both protocols' metrics, penetration, digests, software versions, physics config), "
        "a datasheet (README.md: counts, success, error distributions as plots, failure reasons, versions, every "
        "column with its unit) and SHA256SUMS. Readable with pandas or pyarrow alone; `hoi-refine verify OUT` "
        "checks it. The results come from a folder (--from: every *.result.npz under it) or from a batch through "
        "the API (--batch: every job of it, which must all be finished; jobs that failed get an index row "
        "without a result).",
    )
    e.add_argument("--out", type=Path, required=True, help="the release folder to create (must not exist or be empty)")
    e.add_argument("--from", dest="folder", type=Path, default=None, help="a folder of result files")
    e.add_argument("--batch", default=None, help="a batch id (with --api and --key)")
    e.add_argument("--api", default=os.environ.get("HOI_REFINE_API_URL"),
                   help="the service's base URL (default: HOI_REFINE_API_URL)")
    e.add_argument("--key", default=os.environ.get("HOI_REFINE_API_KEY"),
                   help="API key (default: HOI_REFINE_API_KEY)")
    e.add_argument("--title", default=None, help="the datasheet's title (default: from the batch or folder name)")
    e.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from service.dataset.export import export_release

    if (args.folder is None) == (args.batch is None):
        raise ConfigurationError("give one source: --from FOLDER or --batch ID")
    console = Console(stderr=True)
    columns = (TextColumn("export"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        if args.folder is not None:
            from service.dataset.sources import folder_items

            if not args.folder.is_dir():
                raise ConfigurationError(f"{args.folder} is not a folder")
            task = progress.add_task("export", total=None)
            summary = export_release(folder_items(args.folder), args.out, source=f"the folder {args.folder.name}",
                                     title=args.title or f"Dataset release: {args.folder.name}",
                                     on_item=lambda _: progress.advance(task))
        else:
            from common.api_client import ApiClient
            from service.dataset.sources import batch_items, batch_jobs

            if not args.api or not args.key:
                raise ConfigurationError("--batch needs --api and --key (or HOI_REFINE_API_URL / HOI_REFINE_API_KEY)")
            with ApiClient(args.api, args.key) as client:
                batch = client.batch(args.batch)
                jobs = batch_jobs(client, args.batch)
                task = progress.add_task("export", total=len(jobs))
                name = batch.get("name") or args.batch
                summary = export_release(batch_items(client, jobs), args.out, source=f"the batch {name}",
                                         title=args.title or f"Dataset release: {name}",
                                         on_item=lambda _: progress.advance(task))
    Console().print(f"release {summary.out}: {summary.sequences} sequences ({summary.with_result} with a result), "
                    f"{summary.contacts} contacts, {summary.files} files; check it with `hoi-refine verify "
                    f"{summary.out}`")
    return 0
