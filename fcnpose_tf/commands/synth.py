"""Render a synthetic UR5 dataset: PNG frames plus a VIA project file with the 8 keypoints.

A UR5 posed by forward kinematics from its published DH parameters, seen by a
webcam-like camera in a workshop (floors, walls, clutter, a person who sometimes
hides part of the arm, light, blur, noise): by default one fixed cell and camera
(--scene-seed) with the arm in a new pose every frame, as in the paper's data. Writes OUT/images/*.png and
OUT/ur5_synth.json, a folder every --data option accepts. The same --seed gives
byte-identical files for any --workers. See docs/synthetic.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "synth"
OUTPUTS = ("out", "preview")
FILE_OUTPUTS = ("preview",)
"""The outputs that name files: one that exists is refused (without --force) before anything heavy is imported."""
"""Options naming what the command creates: removed again if it fails or is stopped before completing them."""
EXAMPLES = """\
  fcnpose-tf synth --out data/synth --n 500 --seed 0          # training frames, 640x480
  fcnpose-tf synth --out data/synth_test --n 100 --seed 1     # a held-out set from another seed
  fcnpose-tf synth --out demo --n 50 --preview demo_preview.png
  fcnpose-tf synth --out data/synth --n 500 --force --workers 1
  fcnpose-tf synth --out data/random --n 500 --scene random   # a new room and camera per frame
  fcnpose-tf synth --out data/varied --n 4000 --scene random --looks varied    # the generalist's variety
  fcnpose-tf synth --out data/unseen --n 300 --looks heldout --labels kinematic  # a look never pretrained on
  fcnpose-tf synth --out data/seq --n 300 --motion 30         # 10 s of the arm at work, 30 FPS, + motion.mp4
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fcnpose_tf.data.synth.looks import DEFAULT_LABELS, DEFAULT_LOOKS, LABEL_CONVENTIONS, LOOKS

    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="output folder (created; must be empty unless --force)")
    parser.add_argument("--n", type=int, default=500, help="number of frames")
    parser.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same files")
    parser.add_argument("--width", type=int, default=640, help="frame width in pixels")
    parser.add_argument("--height", type=int, default=480, help="frame height in pixels")
    parser.add_argument("--workers", type=int, default=None,
                        help="rendering processes (default: one per CPU core)")
    from fcnpose_tf import settings

    settings.FORCE.variant(help="write into a non-empty folder, replacing an earlier synthetic set").add_to(parser)
    parser.add_argument("--preview", type=Path, metavar="PNG",
                        help="also write a grid of the first 6 frames with keypoints and skeleton drawn")
    parser.add_argument("--no-progress", dest="quiet", action="store_true", default=argparse.SUPPRESS,
                        help=argparse.SUPPRESS)  # --quiet's name before every command had it
    parser.add_argument("--scene", choices=("workcell", "random"), default="workcell",
                        help="workcell: one robot cell filmed by one fixed camera, as in the paper (the default); "
                             "random: a new cell and camera for every frame (domain randomisation)")
    parser.add_argument("--scene-seed", type=int, default=0, metavar="S",
                        help="which workcell (robot look, mount, room, light, camera); frames of every --seed "
                             "share it, so a held-out set is the same cell in new poses")
    parser.add_argument("--looks", choices=LOOKS, default=DEFAULT_LOOKS,
                        help="look family: classic (a silver UR5 with blue-grey caps, a webcam), "
                             "varied (UR3/5/10/16 and e-series arms, any paint, grippers, vacuum cups, spindles, "
                             "lenses, lights and sensors: what the generalist is pretrained on), heldout (a look "
                             "pretraining never draws: a UR5e with dark housings and coloured caps, an adaptive "
                             "gripper, a wide-angle distorting lens, overhead light, a clean render)")
    parser.add_argument("--labels", choices=LABEL_CONVENTIONS, default=DEFAULT_LABELS,
                        help="keypoint convention: housing (the centre of each joint housing, where an annotator "
                             "clicks) or kinematic (the URDF joint frames on the joint axes, as DREAM "
                             "and robot simulators define them)")
    parser.add_argument("--motion", type=float, metavar="FPS",
                        help="a motion sequence: consecutive frames of the workcell's arm moving smoothly through "
                             "its task at this frame rate (nobody beside it), also written as OUT/motion.mp4; "
                             "for smoothing and jitter measurements (docs/runtime.md)")
    parser.add_argument("--tight-framing", type=float, default=0.0, metavar="RATE",
                        help="share of frames framed so tightly that 1-2 keypoints fall outside (unannotated)")


def run(args: argparse.Namespace) -> int:
    from fcnpose_tf.data.synth import generate_dataset, write_preview
    from fcnpose_tf.tables import format_table

    if args.preview is not None:
        from fcnpose_tf.fileio import check_writable

        check_writable(args.preview, force=args.force)  # fail before rendering, not after
    report = generate_dataset(args.out, n=args.n, seed=args.seed, width=args.width, height=args.height,
                              workers=args.workers, force=args.force,
                              tight_framing=args.tight_framing, scene=args.scene, scene_seed=args.scene_seed,
                              looks=args.looks, labels=args.labels, motion_fps=args.motion)
    print(format_table(["Synthetic UR5 set", "Value"], report.summary_rows()))
    print(f"VIA project: {report.via_path}")
    if args.preview is not None:
        print(f"Preview:     {write_preview(report, args.preview, force=args.force)}")
    return 0
