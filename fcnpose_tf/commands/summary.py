"""Print the paper-style layer table, parameters, MACs and file size of a model.

Without MODEL, the unpruned FCN-Pose at the given --input-size (default 224; HxW for another aspect). A model's
view (the crop of the frame it sees, if any) is printed under its table.
MACs are multiply-accumulates of all convolutions for one frame; FLOPs = 2 x MACs.
"""

from __future__ import annotations

import argparse

NAME = "summary"
USES_TENSORFLOW = True
EXAMPLES = """\
  fcnpose-tf summary                                  # the paper's FCN-Pose at 224x224
  fcnpose-tf summary --input-size 64
  fcnpose-tf summary --input-size 224x288             # a 4:3 input: 1.29x the MACs of 224x224
  fcnpose-tf summary --architecture fcn-pose-skip     # with the half-resolution skip before conv10
  fcnpose-tf summary saved_models/fcnpose_ur5.keras   # a trained or pruned model
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.bundled import KERAS_SUFFIXES, model_argument, names_help

    parser.add_argument("model", nargs="?", type=model_argument(KERAS_SUFFIXES), metavar="MODEL",
                        help=f"a .keras/.h5 model file, or a bundled one by name ({names_help(KERAS_SUFFIXES)}); "
                             "default: build FCN-Pose")
    from fcnpose_tf.settings import input_size_or_auto

    parser.add_argument("--input-size", type=input_size_or_auto, default=224, metavar="S|HxW",
                        help="input when building the default model: S (S x S) or HxW, multiples of 32")
    from fcnpose_tf import settings

    settings.ARCHITECTURE.variant(help="the network built without MODEL: " + settings.ARCHITECTURE.help).add_to(parser)


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.preprocess import FrameView
    from fcnpose_tf.training.model import (ARCHITECTURES, build_fcn_pose, describe, given_schema, load_model, schema_of,
                                           view_of)
    from fcnpose_tf.tables import format_table

    if args.model is None:
        if args.input_size == "auto":
            raise UserError("--input-size auto is chosen from a dataset (train, data inspect); give S or HxW here")
        view = FrameView.of(args.input_size)
        model = build_fcn_pose(input_size=view.shape, skip=ARCHITECTURES[args.architecture])
        name = "FCN-Pose with the half-resolution skip" if ARCHITECTURES[args.architecture] else "FCN-Pose"
        title = f"Model: {name} (unpruned, {view.height}x{view.width})"
    else:
        model = load_model(args.model)
        title = f"Model: {args.model}"
    rows = describe(model)
    print(title)
    print(format_table(["Layer", "Type", "Output shape", "Parameters", "MACs"],
                       [(r.name, r.kind, str(r.output_shape), r.params, r.macs) for r in rows]))
    total_params = sum(r.params for r in rows)
    total_macs = sum(r.macs for r in rows)
    print(f"Total parameters: {total_params:,}")
    print(f"MACs per frame:   {total_macs:,} ({total_macs / 1e6:.1f} M; FLOPs = 2 x MACs = {2 * total_macs / 1e6:.1f} M)")
    if args.model is not None:
        size = args.model.stat().st_size
        print(f"File size:        {size:,} bytes ({size / 1e6:.3f} MB)")
        print(f"View:             {view_of(model).describe()}")
        schema = schema_of(model)
        print(f"Keypoints:        {', '.join(schema.keypoints)} (schema {schema.name!r}"
              f"{'' if given_schema(model) is not None else ', not named by the file: the default'})")
    return 0
