"""Build ``worker/hand/data/pose_basis.npz`` from the DexYCB development data (``make pose-basis``).

Runs the retargeting IK over the dev sequences in ``../shared/data/dexycb/dev`` (or ``--data``), takes every
``--stride``-th valid frame, maps left hands into the right hand's convention (``worker.hand.model.MIRROR_SIGNS``:
a left hand mirroring a right hand at ``q`` is at ``MIRROR_SIGNS * q``, so abductions and twists are negated),
fits a PCA and stores it with its provenance (data used, sides, frame count, date, git commit). The basis is
the right hand's; ``worker.refine.prepare.pose_basis`` mirrors it for left hands.

The packaged file was built with ``--sequence-stride 5``, which on the dev split's file order picks 100 right
hands and no left hand (issue #15): a right-hand basis, which is what the refinement assumes.
"""

from __future__ import annotations

import argparse
import datetime as dt
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from worker.hand.pose_basis import POSE_BASIS_FILE, fit_pose_basis, save_pose_basis


def _hinges(args: tuple[str, int]) -> tuple[np.ndarray, str]:
    """Hinge angles of every ``stride``-th valid frame, in the right hand's convention, and the hand side."""
    from common.dexycb import load_dexycb_npz
    from worker.hand.retarget import retarget_hand

    path, stride = args
    seq = load_dexycb_npz(path)
    from worker.hand.model import MIRROR_SIGNS

    ref = retarget_hand(seq, seq.hands[0])
    idx = np.flatnonzero(ref.valid)[::stride]
    return ref.q[idx] * (MIRROR_SIGNS if ref.side == "left" else 1.0), ref.side


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    from common.dexycb import shared_data_dir

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=None, help="folder of DexYCB dev NPZs")
    parser.add_argument("--stride", type=int, default=3, help="use every n-th valid frame (default 3)")
    parser.add_argument("--limit", type=int, default=0, help="use only the first n sequences (0 = all)")
    parser.add_argument("--sequence-stride", type=int, default=1, help="use every n-th sequence (default 1 = all)")
    parser.add_argument("--components", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=POSE_BASIS_FILE)
    args = parser.parse_args(argv)
    data = args.data
    if data is None:
        root = shared_data_dir()
        if root is None:
            print("no DexYCB data: pass --data or provide ../shared/data", file=sys.stderr)
            return 2
        data = root / "dexycb" / "dev"
    files = sorted(data.glob("*.npz"))
    files = files[:: args.sequence_stride]
    if args.limit:
        files = files[: args.limit]
    if not files:
        print(f"no .npz files in {data}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        chunks = list(pool.map(_hinges, [(str(f), args.stride) for f in files], chunksize=4))
    q = np.concatenate([c for c, _ in chunks])
    sides = [side for _, side in chunks]
    provenance = {
        "data": f"DexYCB development split ({data.name}/): {len(files)} sequences (every {args.sequence_stride})",
        "sequences": len(files),
        "subjects": sorted({f.name.split("__")[0] for f in files}),
        "sides": {side: sides.count(side) for side in sorted(set(sides))},
        "convention": "right hand (left hands' abductions and twists negated)",
        "frames": int(q.shape[0]),
        "frame_stride": args.stride,
        "method": "worker.hand.retarget IK (built-in hand), PCA of the 45 hinge angles",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "git_commit": _git_commit(),
        "command": "python -m worker.hand.pose_basis_build " + " ".join(argv if argv is not None else sys.argv[1:]),
    }
    basis = fit_pose_basis(q, args.components, provenance)
    save_pose_basis(args.out, basis)
    top = ", ".join(f"{v:.2f}" for v in basis.explained_variance_ratio[:10])
    print(f"wrote {args.out}: {q.shape[0]} frames from {len(files)} sequences; variance ratio of PC1-10: {top}")
    print(f"first 10 components explain {basis.explained_variance_ratio[:10].sum():.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
