"""Keypoint schemas: the names of a robot's keypoints and the skeleton edges between them. numpy only.

A schema is data a dataset carries (it is stored in the dataset's VIA file
attributes and in model reports); the network's number of output maps follows
it: one map per keypoint plus one skeleton map, keypoint maps first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

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
        try:
            return cls(str(data["name"]), tuple(str(k) for k in data["keypoints"]),
                       tuple((int(a), int(b)) for a, b in data["edges"]))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            shown = repr(data) if len(repr(data)) <= 200 else repr(data)[:200] + "..."
            raise UserError(f"invalid keypoint schema {shown}: expected name, keypoints (a list of names) and "
                            f"edges (pairs of keypoint numbers) ({entry_problem(exc)})") from None


UR5 = KeypointSchema.chain("ur5", ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3", "flange", "tool"))
"""The paper's 8 UR5 keypoints, base to tool, joined in a chain."""


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
