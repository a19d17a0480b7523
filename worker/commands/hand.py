"""``hoi-refine hand pack allegro|leap|FILE --out packed.json``: a robot hand description with its model compiled
and inlined, the form that travels with a job (``submit --hand``, the API's
``options.hand``) and that results embed; ``hoi-refine hand check``: the same checks, nothing written."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from common.settings import get_settings


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("hand", help="check or pack a robot hand description (issue #55)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="hand_command", required=True)
    for name, helptext in (("pack", "compile the model and write the packed description"),
                           ("check", "check a description against its model")):
        q = sub.add_parser(name, help=helptext)
        q.add_argument("hand", help="allegro, leap (models from --robot-dir) or a description file (JSON/YAML)")
        q.add_argument("--robot-dir", type=Path, default=None, help="default HOI_REFINE_ROBOT_DIR")
        if name == "pack":
            q.add_argument("--out", type=Path, required=True, help="packed description to write (.json)")
        q.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from worker.robot import Embodiment, resolve_hand

    packed = resolve_hand(args.hand, args.robot_dir or get_settings().robot_dir)
    if packed is None:
        print("the human hand needs no description")
        return 0
    emb = Embodiment.from_description(packed, packed.model_side)
    print(f"{packed.name}: {emb.num_joints} actuated joints, {len(emb.keypoint_ids)} keypoint sites "
          f"({', '.join(packed.keypoint_order())}), packed model {len(packed.model_xml or '')} characters")
    if args.hand_command == "pack":
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(packed.model_dump(mode="json")))
        print(f"wrote {args.out}")
    return 0
