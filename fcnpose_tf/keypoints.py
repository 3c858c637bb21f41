"""Keypoint schemas: the names of a robot's keypoints and the skeleton edges between them, and how long a serial
robot's limbs are in frames (`LimbPrior`). numpy only.

A schema is data a dataset carries (it is stored in the dataset's VIA file
attributes, in the model files trained on it and in their reports); the network's
number of output maps follows it: one map per keypoint plus one skeleton map,
keypoint maps first.
"""

from __future__ import annotations

import json
import os
import re
import unicodedata
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import entry_problem


@dataclass(frozen=True)
class KeypointSchema:
    """Names of a robot's keypoints in chain order and the skeleton edges (index pairs) between them."""

    name: str
    keypoints: tuple[str, ...]
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self):
        if len(self.keypoints) < 1 or len(set(self.keypoints)) != len(self.keypoints):
            raise UserError(f"schema {self.name!r}: keypoint names must be non-empty and unique")
        for text in (self.name, *self.keypoints):  # names reach messages, tables and files as they are
            if not text or any(unicodedata.category(ch) in ("Cc", "Cs", "Zl", "Zp") for ch in text):
                raise UserError(f"schema {self.name!r}: name {text!r} is empty or holds a control character (a "
                                "line break, tab or NUL) or a lone surrogate (no UTF-8: OpenCV's drawing of it "
                                "crashed); keypoint names are text on one line")
        n = len(self.keypoints)
        for a, b in self.edges:
            if not (0 <= a < n and 0 <= b < n) or a == b:
                raise UserError(f"schema {self.name!r}: edge ({a}, {b}) does not join two of its {n} keypoints")

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def num_maps(self) -> int:
        """Output maps of a model for this schema: one per keypoint plus the skeleton map."""
        return len(self.keypoints) + 1

    @property
    def mirror(self) -> tuple[int, ...]:
        """Where each keypoint's label goes when the frame is flipped left-right: its partner's index for a left/right
        pair (`mirrored_name`: `gripper L` and `gripper R`, `left_finger` and `right_finger`), else its own. A
        flip without the swap would teach the model to put the left finger on the right one. UR5's chain has no
        pair: the identity. Always a permutation: a keypoint is swapped only with one whose partner it is in turn
        (`finger r` beside `finger L` and `finger R` keeps its label rather than taking finger L's)."""
        names, folded = self.keypoints, [name.casefold() for name in self.keypoints]

        def partner(name: str) -> int | None:  # the same spelling first, else any case: `Gripper Left`, `gripper right`
            other = mirrored_name(name)
            if other is None:
                return None
            return names.index(other) if other in names else (
                folded.index(other.casefold()) if other.casefold() in folded else None)

        partners = [partner(name) for name in names]
        return tuple(j if j is not None and partners[j] == i else i for i, j in enumerate(partners))

    def index(self, name: str) -> int:
        """Position of a keypoint name; UserError naming the known labels if it is unknown."""
        try:
            return self.keypoints.index(name)
        except ValueError:
            raise UserError(f"unknown keypoint label {name!r}; expected one of {', '.join(self.keypoints)}") from None

    @classmethod
    def chain(cls, name: str, keypoints: Sequence[str]) -> "KeypointSchema":
        """A serial robot: consecutive keypoints joined by skeleton edges."""
        kps = tuple(keypoints)
        return cls(name, kps, tuple((i, i + 1) for i in range(len(kps) - 1)))

    def to_dict(self) -> dict:
        return {"name": self.name, "keypoints": list(self.keypoints), "edges": [list(e) for e in self.edges]}

    @classmethod
    def from_dict(cls, data: dict) -> "KeypointSchema":
        def listed(value, kind) -> bool:  # as JSON holds them: no str(1) for a name, no int(1.9) for an index
            return isinstance(value, list) and all(isinstance(v, kind) and not isinstance(v, bool) for v in value)

        try:
            name, keypoints, edges = data["name"], data["keypoints"], data["edges"]
            if not (isinstance(name, str) and listed(keypoints, str) and listed(edges, list)
                    and all(len(edge) == 2 and listed(edge, int) for edge in edges)):
                raise TypeError("a schema entry of another kind")
            return cls(name, tuple(keypoints), tuple((a, b) for a, b in edges))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            shown = repr(data) if len(repr(data)) <= 200 else repr(data)[:200] + "..."
            raise UserError(f"invalid keypoint schema {shown}: expected name, keypoints (a list of names) and "
                            f"edges (pairs of keypoint numbers) ({entry_problem(exc)})") from None


_SIDES = {"left": "right", "right": "left", "l": "r", "r": "l", "lft": "rgt", "rgt": "lft"}


_WORD_BREAK = r"([\s_.-]+|(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z]))"
"""Where one word of a keypoint's name ends: separators, or a camel-case capital (`left|Finger`, `R|Wrist`); the
separators are kept (captured, an empty one at a capital) so the name is rebuilt as written."""

_AXIS_WORDS = {"axis", "axle", "joint", "j"}
"""Words beside a single letter that make it an axis's name, not a side (Yaskawa's L and R axes: `L-axis`)."""


def mirrored_name(name: str) -> str | None:
    """The name of the keypoint on the other side: each left/right word of `name` (`left`, `right`, `lft`, `rgt`,
    or `L`/`R` beside another word; whole words between spaces, `_`, `-` or `.` or in camel case (`leftFinger`,
    OpenPose's `RWrist`), any case, a number after it kept: `finger L1`) swapped for the other side's, in the same
    case; None when it has none. A lone letter (`L`, Yaskawa's lower-arm axis) or a letter beside an axis word
    (`L-axis`, `joint R`) names an axis, not a side.

    Example:
        >>> mirrored_name("gripper L"), mirrored_name("Left_finger"), mirrored_name("elbow"), mirrored_name("L-axis")
        ('gripper R', 'Right_finger', None, None)
        >>> mirrored_name("leftFinger"), mirrored_name("RWrist"), mirrored_name("wristRoll")
        ('rightFinger', 'LWrist', None)
    """
    parts = re.split(_WORD_BREAK, name)
    words = [part.lower() for part in parts[::2] if part]
    swapped = False
    for i, part in enumerate(parts):
        word, number = re.fullmatch(r"(.*?)(\d*)", part).groups()  # `L1`: the side L of the first pair
        other = _SIDES.get(word.lower())
        if other is None or i % 2:
            continue
        if len(word) == 1 and (len(words) < 2 or _AXIS_WORDS & set(words)):
            continue
        parts[i] = (other.upper() if word.isupper() else other.capitalize() if word[:1].isupper() else other) + number
        swapped = True
    return "".join(parts) if swapped else None


def describe_mirror(schema: "KeypointSchema") -> str | None:
    """The left/right pairs a flip swaps (`KeypointSchema.mirror`), for `train` and `data inspect` to say: "gripper L
    <-> gripper R"; None without a pair."""
    pairs = [(schema.keypoints[i], schema.keypoints[j]) for i, j in enumerate(schema.mirror) if i < j]
    return ", ".join(f"{a} <-> {b}" for a, b in pairs) or None


UR5 = KeypointSchema.chain("ur5", ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3", "flange", "tool"))
"""The paper's 8 UR5 keypoints, base to tool, joined in a chain."""


def schema_for_maps(num_maps: int) -> KeypointSchema:
    """The schema of a model that names none (`named_schema` found nothing): UR5 for 9 maps, else a chain of generic
    names kp0..kpN (one map per keypoint + skeleton).

    Args:
        num_maps: the model's output maps.
    Returns:
        The schema.
    Raises:
        UserError: fewer than 2 maps (no keypoint map beside the skeleton's): no FCN-Pose model.
    """
    if num_maps < 2:
        raise UserError(f"a model of {num_maps} output map(s) is no FCN-Pose keypoint model: it has one map per "
                        "keypoint plus the skeleton map, at least 2")
    if num_maps == UR5.num_maps:
        return UR5
    return KeypointSchema.chain("generic", [f"kp{i}" for i in range(num_maps - 1)])


def named_schema(num_maps: int, stored: bytes | str | None, model_path: str | os.PathLike) -> KeypointSchema | None:
    """The keypoints a model file names for its maps: the schema stored in the file (`training.model.SCHEMA_ENTRY`
    of a .keras or .h5, `runtime.tflite_metadata.SCHEMA_METADATA` of a .tflite: files written since 2026-12-05),
    else the one its training record names (`records.training_record`: a file written before). Without either,
    `schema_for_maps` is the caller's.

    Args:
        num_maps: the model's output maps.
        stored: the stored entry (the JSON of `KeypointSchema.to_dict`), None when the file has none.
        model_path: the model file, for its training record and for messages.
    Returns:
        The schema, or None.
    Raises:
        UserError: a stored entry that is no schema, or one whose keypoints do not fit the maps.
    """
    from fcnpose_tf.records import recorded_schema

    if stored is not None:
        try:
            data = json.loads(stored)
        except (ValueError, RecursionError) as exc:
            raise UserError(f"{model_path}: its stored keypoint schema is not JSON ({entry_problem(exc)})") from None
        try:
            schema = KeypointSchema.from_dict(data)
        except UserError as exc:
            raise UserError(f"{model_path}: {exc}") from None
        if schema.num_maps != num_maps:
            raise UserError(f"{model_path}: its stored keypoint schema {schema.name!r} has {schema.num_keypoints} "
                            f"keypoints, but the model has {num_maps} output maps ({num_maps - 1} keypoints + "
                            "skeleton)")
        return schema
    recorded = recorded_schema(model_path)
    if isinstance(recorded, dict):
        try:
            schema = KeypointSchema.from_dict(recorded)
        except UserError:  # a hand-edited record: no names rather than a refusal
            return None
        if schema.num_maps == num_maps:
            return schema
    return None


def _spelling(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


def spelling_hint(names: Sequence[str], reference: Sequence[str] = UR5.keypoints, whose: str = "UR5's") -> str | None:
    """When `names` are the `reference` keypoints spelt another way (`wrist_1`, `Wrist-1` for `wrist1`: the same
    letters and digits, in the same order) but not the same strings, a sentence that says so and how to fix it;
    else None. Such names make a new schema, which no model trained on `reference` can start."""
    names, reference = list(names), list(reference)
    if names == reference or [_spelling(n) for n in names] != [_spelling(n) for n in reference]:
        return None
    pairs = [(a, b) for a, b in zip(names, reference) if a != b]
    more = ", ..." if len(pairs) > 3 else ""
    return (f"did you mean {', '.join(b for _, b in pairs[:3])}{more}? The keypoint names differ from {whose} only "
            f"in spelling ({', '.join(f'{a} for {b}' for a, b in pairs[:3])}{more}): rename them in the VIA file's "
            "keypoint options and points")


def keypoint_difference(names: Sequence[str], reference: Sequence[str], names_owner: str = "the model",
                        reference_owner: str = "the data") -> str | None:
    """How two lists of keypoint names differ, in words, or None when they are the same list. When they differ only
    in spelling, `spelling_hint`'s sentence says to rename `reference`'s (a VIA file's) to `names`'.

    Args:
        names: keypoint names in their order (a model's maps, a file's dropdown).
        reference: the names they are compared with.
        names_owner, reference_owner: how the sentence names their owners ("arm.keras", "the data").
    Returns:
        "the same keypoints in another order (...)", or what each side lacks; None when equal.
    """
    names, reference = tuple(names), tuple(reference)
    if names == reference:
        return None
    if set(names) == set(reference):
        return (f"the same keypoints in another order: {names_owner} ({', '.join(names)}) and {reference_owner} "
                f"({', '.join(reference)})")
    extra = [n for n in names if n not in reference]
    missing = [n for n in reference if n not in names]
    parts = ([f"{reference_owner} lacks {', '.join(extra)}"] if extra else []) + (
        [f"{names_owner} lacks {', '.join(missing)}"] if missing else [])
    hint = spelling_hint(reference, names, f"{names_owner}'s")
    return "; ".join(parts) + (f"; {hint}" if hint else "")


@dataclass(frozen=True)
class LimbPrior:
    """How long a serial chain's limbs are in labelled frames: per skeleton edge (keypoint k to k + 1) the mean and the
    standard deviation of log(length / the keypoints' box side, max(w, h)), both in frame pixels."""

    mean: tuple[float, ...]
    sd: tuple[float, ...]

    @classmethod
    def of(cls, keypoints: np.ndarray) -> "LimbPrior":
        """The prior of N x K x 2 labelled keypoints (frame pixels, NaN where unlabelled).

        Raises:
            UserError: fewer than 2 keypoints per frame, or an edge labelled in fewer than 2 frames.
        """
        kps = np.asarray(keypoints, np.float64)
        if kps.ndim != 3 or kps.shape[1] < 2 or kps.shape[2] != 2:
            raise UserError(f"expected N x K x 2 keypoints with K >= 2, got shape {kps.shape}")
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a frame with no labels: its box is NaN
            side = np.nanmax(np.nanmax(kps, axis=1) - np.nanmin(kps, axis=1), axis=1)
            logs = np.log(np.linalg.norm(kps[:, 1:] - kps[:, :-1], axis=2) / side[:, None])
        logs[~np.isfinite(logs)] = np.nan
        if (np.isfinite(logs).sum(axis=0) < 2).any():
            raise UserError("every limb needs both its keypoints labelled in at least 2 frames for its lengths")
        return cls(tuple(float(v) for v in np.nanmean(logs, axis=0)), tuple(float(v) for v in np.nanstd(logs, axis=0)))

    @classmethod
    def pooled(cls, priors: Sequence["LimbPrior"]) -> "LimbPrior":
        """One prior weighing each of `priors` equally (label conventions, say): the mean of their means, the
        spread of their lengths and of their means together."""
        means, sds = np.array([p.mean for p in priors]), np.array([p.sd for p in priors])
        sd = np.sqrt((sds ** 2).mean(axis=0) + means.var(axis=0))
        return cls(tuple(float(v) for v in means.mean(axis=0)), tuple(float(v) for v in sd))


UR5_LIMBS = LimbPrior(mean=(-1.886, -0.605, -0.776, -2.242, -2.535, -2.354, -1.924),
                      sd=(0.476, 0.323, 0.448, 0.616, 0.685, 0.541, 0.719))
"""The UR5's limbs (base-shoulder, ..., flange-tool) in generated frames that vary in every way the generator
varies them: `LimbPrior.pooled` of the two label conventions, `synth --scene random --n 2400 --seed 80000` (the
visible joint caps) and `synth --scene random --looks varied --labels kinematic --n 480 --seed 70000` (the kinematic
joint frames); `python tools/limb_prior.py DATA DATA` prints it. What `postprocess`'s chained cluster choice
(`Decoding(cluster="chain")`) holds a pair of clusters' distance to (docs/postprocess.md, "`--cluster
chain`")."""
