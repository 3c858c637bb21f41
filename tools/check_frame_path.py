#!/usr/bin/env python
"""Are the runtime's keypoints unchanged, bit for bit? For changes that should only make the frame path faster.

    python tools/check_frame_path.py --out before.npz                      # on the code before the change
    python tools/check_frame_path.py --out after.npz --compare before.npz  # after it: exit 1 on any difference

Runs every .tflite file (default: the bundled ones) through `KeypointModel.predict` (preprocessing,
forward pass, post-processing: the runtime's own frame path, 1 thread) on the frames of a dataset
(default: the held-out synthetic frames) and stores the keypoints in frame pixels and the
confidences. --compare checks them against an earlier run with `np.array_equal` (NaN equal to NaN):
the same files and frames must give the same bits.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tflite", type=Path, action="append", help="a .tflite file; repeat (default: bundled)")
    parser.add_argument("--data", type=Path, help="dataset whose frames are used (default: held-out synthetic)")
    parser.add_argument("--out", type=Path, required=True, help="write the keypoints here (.npz)")
    parser.add_argument("--compare", type=Path, help="an earlier --out to compare with")
    args = parser.parse_args()

    from fcnpose_tf.bundled import models_dir
    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.runtime.estimator import KeypointModel
    from fcnpose_tf.data.synthcache import heldout_data

    paths = args.tflite or sorted(models_dir().glob("*.tflite"))
    dataset = load_dataset(args.data or heldout_data())
    frames = [dataset.load_image(i) for i in range(len(dataset))]
    results = {}
    for path in paths:
        model = KeypointModel(path, num_threads=1)
        predictions = [model.predict(frame) for frame in frames]
        results[f"{path.name}:keypoints"] = np.stack([p.keypoints for p in predictions])
        results[f"{path.name}:confidence"] = np.stack([p.confidence for p in predictions])
        found = int(sum(p.found.sum() for p in predictions))
        print(f"{path.name}: {len(frames)} frames, {found} keypoints found")
    np.savez(args.out, **results)
    if args.compare is None:
        return 0
    with np.load(args.compare) as before:
        differ = sorted(set(before.files) ^ set(results))
        differ += [k for k in sorted(set(before.files) & set(results))
                   if not np.array_equal(before[k], results[k], equal_nan=True)]
    print("bit-identical to " + str(args.compare) if not differ else f"DIFFERENT from {args.compare}: {differ}")
    return 1 if differ else 0


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
