"""Check a dataset (frame and keypoint counts, dropped frames, folds, a preview of the target maps), or merge
rounds of labelling into one VIA project.

DATA is a folder holding one VIA project file (*.json) and its images (beside it
or in images/), or a VIA file path (images beside it, in images/, or --images).
The first look at a dataset stores its splits as <VIA stem>.splits.json beside
the VIA file; every later command reuses them.

`data merge A.json B.json ... --out C.json` joins VIA projects frame by file name (a frame annotated
in two of them is an error unless --prefer last), with every input's image folder stored so C.json
loads with `data inspect C.json` and `train --data C.json` (docs/data.md, "Correcting and merging rounds").
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fcnpose_tf import settings
from fcnpose_tf.data.args import add_data_arguments, load_from_args

NAME = "data"
OUTPUTS = ("out",)
FILE_OUTPUTS = ("out",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
EXAMPLES = """\
  fcnpose-tf data inspect demo                          # counts, drops and folds of a dataset folder
  fcnpose-tf data inspect demo --out preview.png        # plus frames with keypoints, skeleton and maps
  fcnpose-tf data inspect labels.json --images frames/ --keypoint-attr joint --min-visible 6
  fcnpose-tf data inspect my_export.json --skip-bad     # skip frames with bad regions, count them
  fcnpose-tf data merge round1/labels.json round2/pre.json --out merged/labels.json   # rounds into one project
  fcnpose-tf data merge round1/labels.json round2/pre.json --out merged.json --prefer last  # later file wins
"""

MERGE_EXAMPLES = """\
  fcnpose-tf data merge round1/labels.json round2/pre.json --out merged/labels.json
  fcnpose-tf data merge round1/labels.json round2/pre.json --out merged.json --prefer last
  fcnpose-tf data inspect merged/labels.json                 # what the merged project holds, as train reads it
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    inspect = actions.add_parser(
        "inspect", help="counts, dropped frames, folds and a preview PNG", formatter_class=parser.formatter_class,
        description="Load a dataset as training will (same drops, same stored splits), print what it holds "
                    "and optionally write a preview of frames with keypoints, skeleton and target maps.",
        epilog="examples:\n" + EXAMPLES.rstrip())
    settings.add_command_options(inspect)
    add_data_arguments(inspect)
    inspect.add_argument("--out", type=Path, help="write a preview PNG here")
    settings.FORCE.variant(help="overwrite --out if it exists").add_to(inspect)
    inspect.add_argument("--samples", type=int, default=6, help="frames in the preview")
    inspect.add_argument("--input-size", type=settings.input_size_or_auto, default=settings.AUTO_INPUT_SIZE,
                         metavar="auto|S|HxW",
                         help="the model input for the target maps and the preview: auto (default) is what `train` "
                              "would choose for these frames, printed with its reasons; S or HxW (multiples of 32)")
    inspect.add_argument("--crop", choices=settings.TRAIN_CROP.choices, default=settings.TRAIN_CROP.default,
                         help="as train --crop: auto shows a fixed camera's workspace crop with --input-size auto, "
                              "workspace the crop at any input size, none the whole frame")
    inspect.add_argument("--augment-copies", type=int, default=None,
                         help="augmented copies per training frame (for the counts; the preview shows one); default: "
                              "what train on its defaults chooses for these frames")
    inspect.add_argument("--seed", type=int, default=0, help="augmentation seed")

    merge = actions.add_parser(
        "merge", help="merge VIA projects (rounds of labelling) into one", formatter_class=parser.formatter_class,
        description="Join VIA 2 projects frame by file name into one project that train --data and data inspect "
                    "load: images are found as train --data finds them, their folders stored in the merged "
                    "project (relative to it). A frame annotated differently in two inputs is an error naming it "
                    "(or --prefer last); identical annotations are kept once; the inputs must name the same keypoints "
                    "(in any order: the first input's schema is kept).",
        epilog="examples:\n" + MERGE_EXAMPLES.rstrip())
    settings.add_command_options(merge)
    merge.add_argument("inputs", nargs="+", type=Path, metavar="VIA",
                       help="VIA project files (or dataset folders holding one), earliest round first")
    merge.add_argument("--out", type=Path, required=True, metavar="OUT.json", help="the merged VIA project")
    merge.add_argument("--prefer", choices=("error", "last"), default="error",
                       help="a frame annotated differently in two inputs: error, or take the last input's annotation")
    merge.add_argument("--keypoint-attr", default="keypoint", metavar="NAME",
                       help="VIA region attribute holding each point's keypoint name")
    merge.add_argument("--skip-bad", action="store_true",
                       help="leave out frames with bad regions or missing images instead of stopping (listed)")
    settings.FORCE.variant(help="overwrite --out if it exists").add_to(merge)


def run(args: argparse.Namespace) -> int:
    if args.action == "inspect":
        return _inspect(args)
    if args.action == "merge":
        return _merge(args)
    raise AssertionError(args.action)  # pragma: no cover - argparse restricts the choices


def _inspect(args: argparse.Namespace) -> int:
    from collections import Counter

    import numpy as np

    from fcnpose_tf.data.masks import default_radius, default_thickness
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_writable
    from fcnpose_tf.keypoints import describe_mirror, spelling_hint
    from fcnpose_tf.tables import format_table

    settings.TRAIN_INPUT_SIZE.validate(args.input_size)
    if args.samples < 1:
        raise UserError(f"--samples must be at least 1, got {args.samples}")
    if args.augment_copies is not None and args.augment_copies < 0:
        raise UserError(f"--augment-copies must be >= 0, got {args.augment_copies}")
    if args.out is not None:
        check_writable(args.out, args.force)  # fail before the work, not after it
    ds = load_from_args(args)
    schema = ds.schema
    kps = ds.keypoints()
    visible = np.isfinite(kps).all(axis=2)

    folder = {s.image_path.parent for s in ds.samples}
    print(f"Dataset: {ds.via_path}  (images: {', '.join(sorted(map(str, folder)))})")
    print(f"Schema:  {schema.name}, {schema.num_keypoints} keypoints ({', '.join(schema.keypoints)}), "
          f"{schema.num_maps} target maps" + (f"; flips swap {pairs}" if (pairs := describe_mirror(schema)) else ""))
    hint = spelling_hint(schema.keypoints)
    if hint:
        print(f"note: {hint}; as they are, no bundled model can start the training")
    print(f"Frames:  {len(ds)} usable, {ds.num_dropped} dropped "
          f"(threshold: at least {ds.min_visible} of {schema.num_keypoints} keypoints visible)")
    sizes = Counter((s.width, s.height) for s in ds.samples)
    print("Frame sizes: " + ", ".join(f"{w}x{h} ({n})" for (w, h), n in sizes.most_common()))
    if ds.ignored_regions:
        print(f"Ignored {ds.ignored_regions} non-point region(s) (rectangles, polygons, ...)")

    per_frame = Counter(int(v) for v in visible.sum(axis=1))
    print("\nKeypoints per frame")
    print(format_table(["Visible keypoints", "Frames"], sorted(per_frame.items(), reverse=True)))
    print("\nFrames per keypoint")
    print(format_table(["Keypoint", "Annotated frames", "Share"],
                       [(name, int(visible[:, k].sum()), f"{visible[:, k].mean():.1%}")
                        for k, name in enumerate(schema.keypoints)]))
    if ds.dropped:
        print("\nDropped frames")
        print(format_table(["Reason", "Frames"], list(ds.dropped.items())))
        for message in ds.problems[:10]:
            print(f"  {message}")
        if len(ds.problems) > 10:
            print(f"  ... and {len(ds.problems) - 10} more")

    from fcnpose_tf.data.arm_size import resolve_view
    from fcnpose_tf.data.views import FIXED_CAMERA_MAX_VARIATION, choose_augment, view_variation

    variation = view_variation([sample.image_path for sample in ds.samples])
    augment = choose_augment(variation)
    fixed_camera = augment == "paper"
    online = args.augment_copies is None and augment == "online"  # fresh transforms of each frame every epoch
    copies = 0 if online else args.augment_copies if args.augment_copies is not None else \
        settings.train_augment_copies(True, augment, settings.FINE_TUNE_ARCHITECTURE)  # train fine-tunes the generalist
    rows = []
    names = [("hold-out", None)] + [(f"fold {i}", i) for i in range(len(ds.splits.folds))]
    for label, fold in names:
        train, val = ds.split(fold)
        rows.append((label, len(train), len(val), len(train) * (1 + copies)))
    print(f"\nSplits (seed {ds.splits.seed}, {ds.splits.k}-fold and {1 - ds.splits.val_fraction:.0%}/"
          f"{ds.splits.val_fraction:.0%} hold-out; {ds.splits_status}: {ds.splits_path})")
    samples = "Train samples (online augmentation: new transforms every epoch)" if online else \
        f"Train samples (+{copies} copies each)"
    print(format_table(["Split", "Train frames", "Val frames", samples], rows))
    if not ds.splits.folds:
        print(f"  (too few frames for {ds.splits.k} folds)")
    print(f"\nWhat `train` on its defaults chooses for these frames: augmentation {augment} "
          f"({'one fixed camera' if fixed_camera else 'views that vary'}: the frames differ from their median by "
          f"{variation:.2f} std; a fixed camera measures <= {FIXED_CAMERA_MAX_VARIATION}), and")
    view = resolve_view(ds.samples, args.input_size, args.crop, fixed_camera).chose
    short = min(view.shape)
    print(f"Target maps at {view.height}x{view.width}: discs of radius {default_radius(short):.3g} px, skeleton lines "
          f"{default_thickness(short):.3g} px thick (the paper's 6 px and 30 px at 224, scaled)")

    if args.out is not None:
        image = preview_image(ds, args.samples, view, args.seed)
        _write_png(args.out, image, args.force)
        print(f"Preview: {args.out} ({min(args.samples, len(ds))} frames as the model sees them, {view.describe()}; "
              "columns: keypoints and skeleton, target maps, an augmented copy with its maps)")
    return 0


def _merge(args: argparse.Namespace) -> int:
    from fcnpose_tf.correction.merge import merge_via_projects
    from fcnpose_tf.data.via import SPLIT_ATTRIBUTE
    from fcnpose_tf.data.splits import splits_path
    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import check_writable, write_json

    if args.out.suffix.lower() != ".json":
        raise UserError(f"{args.out}: a VIA project is a .json file")
    check_writable(args.out, args.force)  # before reading every input, not after
    result = merge_via_projects(args.inputs, args.out, prefer=args.prefer, attribute=args.keypoint_attr,
                                skip_bad=args.skip_bad)
    stale = splits_path(args.out)
    write_json(args.out, result.project, force=args.force)
    for path, count in result.frames_per_input:
        print(f"{path}: {count} frames")
    notes = []
    if result.identical:
        notes.append(f"{len(result.identical)} annotated identically in two inputs, kept once")
    if result.replaced:
        notes.append(f"{len(result.replaced)} replaced by a later input's annotation (--prefer last): "
                     + ", ".join(result.replaced[:5]) + (", ..." if len(result.replaced) > 5 else ""))
    if result.skipped:
        notes.append(f"{len(result.skipped)} bad frame(s) left out (--skip-bad)")
    if result.roles_kept:
        notes.append(f"{result.roles_kept} keep the training or validation role the inputs' splits gave them "
                     f"(file attribute {SPLIT_ATTRIBUTE}): the merged project validates only on frames no earlier "
                     "round trained on, and new frames fill its validation set")
    print(f"Merged: {args.out}: {result.num_frames} frames, schema {result.schema.name} "
          f"({result.schema.num_keypoints} keypoints)" + (f"; {'; '.join(notes)}" if notes else ""))
    for message in result.skipped[:10]:
        print(f"  left out: {message}")
    print("Images: " + ", ".join(map(str, result.image_folders))
          + (f" ({len(result.stored_with_path)} frame(s) stored with their path: another folder holds an image "
             "of the same name)" if result.stored_with_path else ""))
    if stale.exists():
        print(f"Note: {stale} holds the splits of an earlier {args.out.name}; train and inspect refuse it for the "
              "merged frames: pass --resplit once (or merge into a new file to keep the earlier one's results "
              "comparable)")
    return 0


_TILE = 256
_DOT_SCALE = 1.25  # keypoint dots of 5 px on a 256 px tile


def _overlay_maps(rgb_image, maps):
    """The input image darkened, skeleton map in grey, keypoint discs in their colours (BGR uint8)."""
    import cv2
    import numpy as np

    from fcnpose_tf.draw import keypoint_colour

    base = cv2.cvtColor(rgb_image, cv2.COLOR_RGB2BGR).astype(np.float32) * 0.45
    skeleton = maps[..., -1].astype(bool)
    base[skeleton] = base[skeleton] * 0.5 + 110
    for k in range(maps.shape[-1] - 1):
        disc = maps[..., k].astype(bool)
        base[disc] = keypoint_colour(k)
    return np.ascontiguousarray(np.clip(base, 0, 255).astype(np.uint8))


def _caption(tile, text: str):
    """The tile with a caption strip above it (so no keypoint at the top edge is hidden)."""
    import numpy as np

    from fcnpose_tf.draw import put_text

    strip = np.zeros((18, tile.shape[1], 3), np.uint8)
    put_text(strip, text[:38], (4, 13), 0.42, (255, 255, 255))
    return np.concatenate([strip, tile], axis=0)


def _upscale(image):
    """The image scaled to _TILE rows, its aspect kept."""
    import cv2

    width = int(round(_TILE * image.shape[1] / image.shape[0]))
    return cv2.resize(image, (width, _TILE), interpolation=cv2.INTER_NEAREST if image.shape[0] < _TILE
                      else cv2.INTER_AREA)


def preview_image(dataset, samples: int, input_size, seed: int = 0):
    """A BGR grid: per frame, (keypoints + skeleton | target maps | an augmented copy's maps), plus a legend; each
    tile is the model's input (`input_size`: S, (H, W) or a `FrameView` with its crop) scaled to _TILE rows."""
    import cv2
    import numpy as np

    from fcnpose_tf.data.dataset import TrainingData
    from fcnpose_tf.draw import draw_keypoints, keypoint_colour, put_text, text_size
    from fcnpose_tf.preprocess import FrameView

    view = FrameView.of(input_size)
    count = min(samples, len(dataset))
    indices = np.unique(np.linspace(0, len(dataset) - 1, count).round().astype(int))
    data = TrainingData(dataset, indices, view, augment_copies=1, seed=seed)
    n = len(indices)
    scale = _TILE / view.height
    rows = []
    for j in range(n):
        original, augmented = j, n + j
        left = _upscale(cv2.cvtColor(data.images[original], cv2.COLOR_RGB2BGR))
        left = draw_keypoints(left, data.keypoints[original], dataset.schema, labels=False, scale=_DOT_SCALE,
                              point_scale=scale, copy=False)
        left = _caption(left, dataset.samples[int(indices[j])].filename)
        middle = np.ascontiguousarray(_upscale(_overlay_maps(data.images[original], data.maps[original])))
        middle = _caption(middle, f"target maps ({view.height}x{view.width})")
        right = _upscale(_overlay_maps(data.images[augmented], data.maps[augmented]))
        right = draw_keypoints(right, data.keypoints[augmented], dataset.schema, labels=False, scale=_DOT_SCALE,
                               point_scale=scale, copy=False)
        right = _caption(right, f"augmented: {data.kinds[augmented]}")
        rows.append(np.concatenate([left, middle, right], axis=1))
    grid = np.concatenate(rows, axis=0)
    legend = np.zeros((24, grid.shape[1], 3), np.uint8)
    x = 6
    for k, name in enumerate(dataset.schema.keypoints):
        cv2.circle(legend, (x + 6, 12), 6, keypoint_colour(k), -1, cv2.LINE_AA)
        put_text(legend, name, (x + 16, 16), 0.42, (255, 255, 255))
        x += 24 + text_size(name, 0.42)[0][0]
        if x > legend.shape[1] - 60:
            break
    return np.concatenate([grid, legend], axis=0)


def _write_png(path: Path, image, force: bool) -> None:
    import cv2

    from fcnpose_tf.errors import UserError
    from fcnpose_tf.fileio import write_bytes

    suffix = path.suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise UserError(f"{path}: preview must be a .png (or .jpg) file")
    ok, encoded = cv2.imencode(suffix, image)
    if not ok:  # pragma: no cover - encoding a uint8 image does not fail
        raise UserError(f"{path}: could not encode the preview")
    write_bytes(path, encoded.tobytes(), force=force)
