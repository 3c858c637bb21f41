"""Online keypoint-aware augmentation: fresh random transforms for every sample of every epoch.

The paper augments offline: two fixed rotation/padding copies per training frame, drawn once.
On a few hundred frames of a new arm that set is learnt by heart within a few epochs (see
docs/training.md, "Training on your own frames"). Here each training sample is drawn anew:

    frame (cached once at `work_scale` x the input side)
      ──► geometry (Albumentations, applied to the image and exactly to the keypoints):
          horizontal flip, rotation, zoom in and out, translation; redrawn until every
          visible keypoint stays in the frame (the arm is never cut off)
      ──► resize to the input side (INTER_AREA)
      ──► appearance at the input side (cheap there): brightness/contrast, gamma, hue and
          saturation, channel shuffle, blur, sensor noise, JPEG artefacts, occluding patches
      ──► target maps drawn from the moved keypoints (`masks.make_target_maps`)

A flip swaps the labels of left/right pairs (`keypoints.KeypointSchema.mirror`: `gripper L` and `gripper R`); the
UR5 chain (base ... tool) has none, so its keypoints keep their identities.
Every random choice of sample `i` of epoch `e` comes from a generator seeded with
(seed, e, i), so the same seed gives the same batches, in any order and after a resume.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from fcnpose_tf.data.augment import _albumentations, inside_frame
from fcnpose_tf.data.masks import make_target_maps
from fcnpose_tf.errors import UserError
from fcnpose_tf.preprocess import FrameView, ViewLike, keypoints_to_input
from fcnpose_tf.progress import report_items


@dataclass(frozen=True)
class OnlineAugmentConfig:
    """Ranges of the online augmentation (each transform's probability and strength).

    Geometry: `flip_p` horizontal flip; rotation uniform in ±`max_rotation_deg`; zoom uniform in
    [`min_scale`, `max_scale`] (> 1 zooms in); shift uniform in ±`max_shift` of the side; the
    affine is applied with probability `affine_p` and redrawn up to `max_tries` times until
    every visible keypoint stays inside the frame (then the unwarped frame is used).
    Appearance: `color_p` brightness/contrast/saturation/hue jitter, `gamma_p`, `shuffle_p`
    channel order, `blur_p`, `noise_p`, `jpeg_p`, `dropout_p` one to `max_holes` grey patches of
    up to `max_hole_fraction` of the side (people and tools pass in front of arms).
    """

    flip_p: float = 0.5
    affine_p: float = 0.9
    max_rotation_deg: float = 30.0
    min_scale: float = 0.75
    max_scale: float = 1.3
    max_shift: float = 0.12
    max_tries: int = 10
    color_p: float = 0.8
    hue: float = 0.5
    gamma_p: float = 0.3
    shuffle_p: float = 0.1
    blur_p: float = 0.2
    noise_p: float = 0.3
    jpeg_p: float = 0.3
    dropout_p: float = 0.4
    max_holes: int = 3
    max_hole_fraction: float = 0.2
    work_scale: float = 1.5
    """The frames are cached with each side at least work_scale x the input's (geometry runs there, so zooming in
    keeps detail); the appearance transforms run at the input side."""

    def __post_init__(self) -> None:
        probabilities = ("flip_p", "affine_p", "color_p", "gamma_p", "shuffle_p", "blur_p", "noise_p", "jpeg_p",
                         "dropout_p")
        for name in probabilities:
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise UserError(f"online augmentation: {name} must be a probability in [0, 1], got "
                                f"{getattr(self, name)}")
        if not 0 < self.min_scale <= self.max_scale:
            raise UserError(f"online augmentation: need 0 < min_scale <= max_scale, got {self.min_scale}, "
                            f"{self.max_scale}")
        if not 0 <= self.max_rotation_deg <= 180 or not 0 <= self.max_shift < 1:
            raise UserError("online augmentation: rotation must be in [0, 180] degrees and shift in [0, 1)")
        if self.max_tries < 1 or self.max_holes < 1 or self.work_scale < 1:
            raise UserError("online augmentation: max_tries and max_holes must be >= 1, work_scale >= 1")


def _geometry(config: OnlineAugmentConfig):
    import cv2

    A = _albumentations()
    return A.Compose(
        [A.HorizontalFlip(p=config.flip_p),
         A.Affine(rotate=(-config.max_rotation_deg, config.max_rotation_deg),
                  scale=(config.min_scale, config.max_scale),
                  translate_percent=(-config.max_shift, config.max_shift), keep_ratio=True,
                  interpolation=cv2.INTER_LINEAR, border_mode=cv2.BORDER_CONSTANT, fill=0, p=config.affine_p)],
        keypoint_params=A.KeypointParams(format="xy", remove_invisible=False, check_each_transform=False),
        save_applied_params=True)  # whether the flip ran: left/right pairs swap labels then


def _appearance(config: OnlineAugmentConfig, input_size: int):
    """Colour, blur, noise, compression and holes; `input_size` is the input's shorter side."""
    A = _albumentations()
    hole = max(1, int(round(config.max_hole_fraction * input_size)))
    return A.Compose([
        A.ColorJitter(brightness=0.35, contrast=0.35, saturation=0.4, hue=config.hue, p=config.color_p),
        A.RandomGamma(gamma_limit=(70, 150), p=config.gamma_p),
        A.ChannelShuffle(p=config.shuffle_p),
        A.OneOf([A.GaussianBlur(blur_limit=(3, 5)), A.MotionBlur(blur_limit=(3, 7))], p=config.blur_p),
        A.GaussNoise(std_range=(0.02, 0.08), p=config.noise_p),
        A.ImageCompression(quality_range=(30, 90), p=config.jpeg_p),
        A.CoarseDropout(num_holes_range=(1, config.max_holes), hole_height_range=(max(1, hole // 4), hole),
                        hole_width_range=(max(1, hole // 4), hole), fill="random_uniform", p=config.dropout_p),
    ])


def sample_rng(seed: int, epoch: int, index: int) -> np.random.Generator:
    """The generator of sample `index` of `epoch`: independent of the order samples are drawn in."""
    return np.random.default_rng([int(seed), int(epoch), int(index)])


class OnlineAugmenter:
    """Draws augmented (image, keypoints) pairs at the input size from cached working-size frames."""

    def __init__(self, input_size: ViewLike, config: OnlineAugmentConfig = OnlineAugmentConfig(),
                 mirror: Sequence[int] | None = None):
        self.input_size = FrameView.of(input_size).shape
        self.config = config
        self.mirror = list(mirror) if mirror is not None and list(mirror) != sorted(mirror) else None
        """`KeypointSchema.mirror` when it swaps a pair: the keypoints' order after a flip; None: no pair."""
        self._geometry = _geometry(config)
        self._appearance = _appearance(config, min(self.input_size))

    def _seed(self, compose, rng: np.random.Generator) -> None:
        state = int(rng.integers(2 ** 63))
        compose.set_random_state(np.random.default_rng(state), random.Random(state))

    def __call__(self, image_rgb: np.ndarray, keypoints: np.ndarray, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
        """One augmented sample of a working-size RGB frame.

        Args:
            image_rgb: H x W x 3 uint8 frame (any size; geometry runs at this size).
            keypoints: K x 2 (x, y) in that frame's pixels, NaN rows missing.
            rng: the sample's generator (`sample_rng`).
        Returns:
            (H x W x 3 uint8 RGB image, K x 2 keypoints in input pixels, NaN missing).
        """
        import cv2

        h, w = image_rgb.shape[:2]
        kps = np.asarray(keypoints, np.float64).reshape(-1, 2)
        visible = np.isfinite(kps).all(axis=1)
        warped, moved = image_rgb, kps
        for _ in range(self.config.max_tries):
            self._seed(self._geometry, rng)
            out = self._geometry(image=image_rgb, keypoints=kps[visible].astype(np.float32))
            candidate = np.full_like(kps, np.nan)
            candidate[visible] = np.asarray(out["keypoints"], np.float64).reshape(-1, 2)[:, :2]
            if self.mirror is not None and any(name == "HorizontalFlip" for name, _ in out["applied_transforms"]):
                candidate = candidate[self.mirror]  # the left finger, flipped, is where a right finger is
            if inside_frame(candidate, w, h):
                warped, moved = out["image"], candidate
                break
        small = cv2.resize(np.ascontiguousarray(warped), self.input_size[::-1], interpolation=cv2.INTER_AREA)
        self._seed(self._appearance, rng)
        small = self._appearance(image=small)["image"]
        return np.ascontiguousarray(small), keypoints_to_input(moved, (h, w), self.input_size)


def working_frame(frame_bgr: np.ndarray, keypoints: np.ndarray, input_size: int | tuple[int, int], work_scale: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A frame as cached for online augmentation: RGB, each side at least work_scale x the input's matching side
    (`input_size`: S or (height, width); never enlarged), so a frame of another aspect than the input's is not
    enlarged along one axis by the last resize (a 480 x 640 frame for a 128 x 384 input: 480 px wide, not 192).

    Keypoints scale through the pixel edges, as `preprocess.keypoints_to_input` does.
    """
    import cv2

    h, w = frame_bgr.shape[:2]
    in_h, in_w = (input_size, input_size) if np.isscalar(input_size) else input_size
    factor = min(1.0, work_scale * max(in_h / h, in_w / w))
    size = (max(1, int(round(w * factor))), max(1, int(round(h * factor))))
    rgb = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2RGB)
    if size != (w, h):
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    scale = np.array([size[0] / w, size[1] / h])
    return rgb, (np.asarray(keypoints, np.float64) + 0.5) * scale - 0.5


class OnlineTrainingData:
    """Training frames served with fresh online augmentation every epoch.

    `samples_per_epoch` rows an epoch (default: the frame count times 3, the number of rows the
    paper's two offline copies give), frames visited in a seeded shuffled order.
    """

    def __init__(self, dataset, indices: Iterable[int], input_size: ViewLike, seed: int = 0,
                 config: OnlineAugmentConfig = OnlineAugmentConfig(), samples_per_epoch: int | None = None,
                 radius: float | None = None, thickness: float | None = None, progress: bool = False):
        self.indices = np.asarray(list(indices), dtype=np.int64)
        if not self.indices.size:
            raise UserError("no training frames to augment")
        self.dataset = dataset
        self.schema = dataset.schema
        self.view = FrameView.of(input_size)
        self.input_size = self.view.shape
        self.seed = int(seed)
        self.config = config
        self.samples_per_epoch = int(samples_per_epoch or 3 * len(self.indices))
        if self.samples_per_epoch < 1:
            raise UserError(f"samples per epoch must be positive, got {self.samples_per_epoch}")
        self.radius, self.thickness = radius, thickness
        self.frames: list[np.ndarray] = []
        self.keypoints: list[np.ndarray] = []
        label = f"frames for online augmentation at {self.view.describe(whole='')}"
        for index in report_items(self.indices, progress, label):
            frame, kps = self.view.crop_sample(dataset.load_image(int(index)), dataset.samples[int(index)].keypoints)
            rgb, kps = working_frame(frame, kps, self.input_size, config.work_scale)
            self.frames.append(rgb)
            self.keypoints.append(kps)
        self.augmenter = OnlineAugmenter(self.input_size, config, self.schema.mirror)

    def __len__(self) -> int:
        return self.samples_per_epoch

    @property
    def num_frames(self) -> int:
        return len(self.indices)

    def describe(self) -> str:
        """What one epoch shows, for progress lines."""
        return f"{self.samples_per_epoch} freshly augmented samples an epoch from {self.num_frames} frames"

    def order(self, epoch: int) -> np.ndarray:
        """Which cached frame each row of `epoch` shows (a seeded shuffle, frames repeated to fill the epoch)."""
        rng = np.random.default_rng([self.seed, int(epoch), 0x5EED])
        reps = math.ceil(self.samples_per_epoch / len(self.indices))
        return np.concatenate([rng.permutation(len(self.indices)) for _ in range(reps)])[:self.samples_per_epoch]

    def sample(self, epoch: int, row: int, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(H x W x 3 uint8 image, H x W x C uint8 maps) of row `row` of `epoch`, showing cached frame `frame`."""
        image, kps = self.augmenter(self.frames[frame], self.keypoints[frame], sample_rng(self.seed, epoch, row))
        return image, make_target_maps(kps, self.input_size, self.schema, self.radius, self.thickness)

    def batch(self, epoch: int, rows: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Float32 (images in [0, 1], maps) for rows of `epoch`."""
        frames = self.order(epoch)
        h, w = self.input_size
        images = np.empty((len(rows), h, w, 3), np.float32)
        maps = np.empty((len(rows), h, w, self.schema.num_maps), np.float32)
        for j, row in enumerate(rows):
            image, target = self.sample(epoch, int(row), int(frames[int(row)]))
            np.multiply(image, np.float32(1.0 / 255.0), out=images[j], casting="unsafe")
            maps[j] = target
        return images, maps

    def sequence(self, batch_size: int = 8, shuffle: bool = True, seed: int = 0):
        """A tf_keras Sequence of fresh augmented batches; `epoch` follows Keras' epochs (settable on resume).

        `shuffle` and `seed` are accepted for the same call as `TrainingData.sequence`: the order is
        always the seeded shuffle of this object's seed.
        """
        if batch_size < 1:
            raise UserError(f"batch size must be positive, got {batch_size}")
        return _online_sequence_class()(self, batch_size)


_SEQUENCE_CLASS = None


def _online_sequence_class():
    global _SEQUENCE_CLASS
    if _SEQUENCE_CLASS is None:
        import tf_keras as keras

        class OnlineSequence(keras.utils.Sequence):
            """Batches of freshly augmented samples; epoch counted by on_epoch_end."""

            def __init__(self, data: OnlineTrainingData, batch_size: int):
                super().__init__()
                self.data = data
                self.batch_size = int(batch_size)
                self.epoch = 0

            def __len__(self) -> int:
                return math.ceil(len(self.data) / self.batch_size)

            def __getitem__(self, batch: int):
                if not 0 <= batch < len(self):
                    raise IndexError(f"batch {batch} out of range (0..{len(self) - 1})")
                stop = min(len(self.data), (batch + 1) * self.batch_size)
                return self.data.batch(self.epoch, range(batch * self.batch_size, stop))

            def on_epoch_end(self) -> None:
                self.epoch += 1

        _SEQUENCE_CLASS = OnlineSequence
    return _SEQUENCE_CLASS
