"""The limb lengths of labelled frames, as `fcnpose_tf.keypoints.LimbPrior` holds them.

    python tools/limb_prior.py DATA [DATA ...]

Prints each dataset's prior (per skeleton edge of the serial chain, the mean and the standard deviation of
log(length / the keypoints' box side)) and, for several, `LimbPrior.pooled` of them, each weighing the same:
`keypoints.UR5_LIMBS` is the pooled prior of two generated sets of the two label conventions (its docstring names
them).
"""

from __future__ import annotations

import argparse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="+", help="dataset folders or VIA .json files")
    args = parser.parse_args()

    from fcnpose_tf.data.dataset import load_dataset
    from fcnpose_tf.keypoints import LimbPrior

    def shown(prior: LimbPrior) -> str:
        return (f"LimbPrior(mean=({', '.join(f'{v:.3f}' for v in prior.mean)}), "
                f"sd=({', '.join(f'{v:.3f}' for v in prior.sd)}))")

    priors = []
    for data in args.data:
        dataset = load_dataset(data)
        priors.append(LimbPrior.of(dataset.keypoints()))
        print(f"{data} ({len(dataset)} frames): {shown(priors[-1])}")
    if len(priors) > 1:
        print(f"pooled: {shown(LimbPrior.pooled(priors))}")


if __name__ == "__main__":
    from fcnpose_tf.cli import run_tool

    raise SystemExit(run_tool(main))
