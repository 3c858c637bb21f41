"""Look families: which arm, paint, end effector, camera, light and sensor a synthetic frame is drawn from.

A family is a set of components. `classic` is the generator's original look (a UR5 in silver with
blue-grey caps, a webcam, one key light): the bundled baseline and the old proxies use it. `varied`
randomises everything a third party's arm and camera can differ in and is what the generalist is
pretrained on. `heldout` is a look pretraining never draws, component by component (another UR
generation, dark housings with coloured caps, an adaptive two-finger gripper, a wide-angle lens with
strong barrel distortion, overhead light, a clean render without sensor noise): frames of it measure
how the package does on someone else's arm. `PRETRAINING_LOOKS` lists the families the generalist's
data may come from; `check_pretraining_looks` refuses the others.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, field

import numpy as np

from fcnpose_tf.errors import UserError

PI = math.pi


# ------------------------------------------------------------------------------------------------ arms

@dataclass(frozen=True)
class ArmModel:
    """One robot of the Universal Robots family: published DH parameters and the shapes' proportions.

    d, a, alpha: standard DH parameters (m, m, rad). shoulder_offset: the upper arm's centreline along
    the shoulder/elbow axes from the DH plane; forearm_offset: the forearm's (shoulder offset minus the
    elbow's step back), both from the ROS `ur_description` URDFs. scale: housing and link radii relative
    to the UR5's. housings: per joint (axis frame index, (lo, hi) span along that axis, radius, end faces).
    """

    name: str
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    shoulder_offset: float
    forearm_offset: float
    scale: float
    housings: dict = field(hash=False, compare=False)
    base_span: tuple[float, float] = (0.012, 0.075)
    base_radius: float = 0.0640
    flange_span: tuple[float, float] = (0.070, 0.0823)
    flange_radius: float = 0.0315


_UR5_HOUSINGS = {
    "shoulder": (1, (-0.070, 0.205), 0.0625, ("cap", "cap")),
    "elbow": (2, (-0.045, 0.205), 0.0500, ("cap", "cap")),
    "wrist1": (3, (-0.045, 0.160), 0.0450, ("cap", "cap")),
    "wrist2": (4, (-0.010, 0.150), 0.0450, ("buried", "cap")),
    "wrist3": (5, (-0.010, 0.070), 0.0450, ("buried", "plain")),
}
_ALPHA = (PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0)

UR5_ARM = ArmModel("ur5", (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823), (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0),
                   _ALPHA, 0.13585, 0.13585 - 0.1197, 1.0, _UR5_HOUSINGS)
"""The UR5 (CB3) the generator has always drawn: its shapes are the reference the other arms scale."""


def _arm(name: str, d: tuple[float, ...], a2: float, a3: float, shoulder: float, step: float,
         scale: float) -> ArmModel:
    """An arm whose housings follow the UR5's layout, scaled, with spans reaching its own offsets."""
    s = scale
    housings = {
        "shoulder": (1, (-0.070 * s, shoulder + 0.069 * s), 0.0625 * s, ("cap", "cap")),
        "elbow": (2, (-0.045 * s, shoulder + 0.069 * s), 0.0500 * s, ("cap", "cap")),
        "wrist1": (3, (-0.045 * s, d[3] + 0.051 * s), 0.0450 * s, ("cap", "cap")),
        "wrist2": (4, (-0.010 * s, d[4] + 0.055 * s), 0.0450 * s, ("buried", "cap")),
        "wrist3": (5, (-0.010 * s, d[5] - 0.0123 * s), 0.0450 * s, ("buried", "plain")),
    }
    return ArmModel(name, d, (0.0, a2, a3, 0.0, 0.0, 0.0), _ALPHA, shoulder, shoulder - step, s, housings,
                    base_span=(0.012 * s, d[0] - 0.014 * s), base_radius=0.064 * s,
                    flange_span=(d[5] - 0.0123 * s, d[5]), flange_radius=0.0315 * s)


ARMS: dict[str, ArmModel] = {
    "ur5": UR5_ARM,
    "ur3": _arm("ur3", (0.1519, 0.0, 0.0, 0.11235, 0.08535, 0.0819), -0.24365, -0.21325, 0.1198, 0.0925, 0.72),
    "ur10": _arm("ur10", (0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922), -0.612, -0.5723, 0.220941, 0.1719, 1.22),
    "ur3e": _arm("ur3e", (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921), -0.24355, -0.2132, 0.120, 0.093, 0.76),
    "ur5e": _arm("ur5e", (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996), -0.425, -0.3922, 0.138, 0.131, 1.06),
    "ur10e": _arm("ur10e", (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655), -0.6127, -0.57155, 0.176, 0.137, 1.25),
    "ur16e": _arm("ur16e", (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655), -0.4784, -0.36, 0.176, 0.137, 1.25),
}
"""Universal Robots' published DH parameters (d1, a2, a3, d4, d5, d6) per model, CB3 and e-series."""


# ----------------------------------------------------------------------------------------------- families

@dataclass(frozen=True)
class LookFamily:
    """The components one family draws from (names; each is rendered by the module that owns it)."""

    name: str
    arms: tuple[str, ...]
    paints: tuple[str, ...]
    tools: tuple[str, ...]
    fov_deg: tuple[float, float]
    """Diagonal field of view of the camera."""
    corner_distortion: tuple[float, float]
    """Barrel distortion as the share by which the picture's corners are pulled in (1 - r_d / r_u at the
    corner; 0.1: a corner 10 % nearer the centre than a pinhole puts it), turned into OpenCV's k1 per camera."""
    distorted_share: float
    """Share of cameras with lens distortion."""
    framing: tuple[float, float]
    """Keypoint box / frame size (the larger of the width and height fractions) of a random view."""
    roll_deg: float
    """Standard deviation of the camera's roll."""
    lights: tuple[str, ...]
    sensor: str
    pretraining: bool


FAMILIES: dict[str, LookFamily] = {
    "classic": LookFamily("classic", ("ur5",), ("classic",), ("classic",), (55.0, 78.0), (0.0, 0.0), 0.0,
                          (0.38, 0.72), 2.5, ("classic",), "webcam", True),
    "varied": LookFamily("varied", ("ur3", "ur5", "ur10", "ur3e", "ur10e", "ur16e"), ("mono", "two-tone", "classic"),
                         ("gripper", "gripper3", "vacuum", "spindle", "suction", "none"), (35.0, 88.0),
                         (0.0, 0.10), 0.5, (0.25, 0.9), 5.0, ("key", "key+fill", "overcast"), "varied", True),
    "heldout": LookFamily("heldout", ("ur5e",), ("dark-housings",), ("adaptive2f",), (88.0, 100.0), (0.13, 0.18),
                          1.0, (0.30, 0.80), 2.5, ("overhead",), "clean", False),
}
"""`classic`: the original look; `varied`: the generalist's pretraining variety; `heldout`: never pretrained on."""

LOOKS = tuple(FAMILIES)
DEFAULT_LOOKS = "classic"
PRETRAINING_LOOKS = tuple(name for name, family in FAMILIES.items() if family.pretraining)


def look_family(name: str) -> LookFamily:
    if name not in FAMILIES:
        raise UserError(f"unknown look family {name!r}; expected one of {', '.join(LOOKS)}")
    return FAMILIES[name]


def check_pretraining_looks(name: str) -> LookFamily:
    """The family, if the generalist may be pretrained on it; a held-out family is refused."""
    family = look_family(name)
    if not family.pretraining:
        raise UserError(f"look family {name!r} is held out from pretraining (it measures unseen looks); "
                        f"pretrain on one of {', '.join(PRETRAINING_LOOKS)}")
    return family


LABEL_CONVENTIONS = ("housing", "kinematic")
DEFAULT_LABELS = "housing"
"""`housing`: each joint's keypoint at the centre of its housing on the joint axis, where an annotator
clicks (the generator's original labels); `kinematic`: the URDF link frames of `ur_description`, as
DREAM and robot simulators define them (shoulder at the base axis, elbow and wrist 1 at the forearm's
centreline, wrist 2 and 3 at their DH origins: on the joint axes, inside the housings)."""


def check_labels(name: str) -> str:
    if name not in LABEL_CONVENTIONS:
        raise UserError(f"unknown label convention {name!r}; expected one of {', '.join(LABEL_CONVENTIONS)}")
    return name


# ------------------------------------------------------------------------------------------------ colours

def hsv(h: float, s: float, v: float) -> np.ndarray:
    """RGB (0..1) of a hue in degrees, saturation and value."""
    return np.array(colorsys.hsv_to_rgb((h % 360.0) / 360.0, s, v))


def paint_colours(rng: np.random.Generator, paint: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(link, housing, cap, band) colours of one robot of a paint scheme other than `classic`.

    `mono`: links and housings in one colour; `two-tone`: housings lighter or darker than the links
    but never below a value of 0.3 (dark housings are the held-out look); `dark-housings` (held out):
    near-black housings, light grey links and saturated warm caps.
    """
    if paint == "dark-housings":
        link = np.full(3, rng.uniform(0.72, 0.88)) + rng.normal(0.0, 0.01, 3)
        housing = np.full(3, rng.uniform(0.10, 0.20)) + rng.normal(0.0, 0.008, 3)
        cap = hsv(rng.uniform(0.0, 35.0), rng.uniform(0.7, 0.9), rng.uniform(0.7, 0.9))
        band = np.full(3, rng.uniform(0.04, 0.08))
        return np.clip(link, 0, 1), np.clip(housing, 0, 1), cap, band
    kind = rng.random()
    if kind < 0.55:  # industrial greys, silvers and whites
        link = hsv(rng.uniform(0, 360), rng.uniform(0.0, 0.12), rng.uniform(0.35, 0.95))
    elif kind < 0.85:  # painted arms: orange, yellow, blue, green, red ...
        link = hsv(rng.uniform(0, 360), rng.uniform(0.4, 0.95), rng.uniform(0.45, 0.95))
    else:  # dark links
        link = hsv(rng.uniform(0, 360), rng.uniform(0.0, 0.3), rng.uniform(0.12, 0.35))
    if paint == "two-tone":
        housing = hsv(rng.uniform(0, 360), rng.uniform(0.0, 0.6), rng.uniform(0.3, 0.95))
    else:
        housing = link.copy()
    if housing.max() < 0.3:  # a dark housing is the held-out look: lift it
        housing = housing + (0.3 - housing.max())
    cap = hsv(rng.uniform(0, 360), rng.uniform(0.0, 0.9), rng.uniform(0.1, 0.9))
    band = np.full(3, rng.uniform(0.05, 0.3))
    return link, housing, cap, band
