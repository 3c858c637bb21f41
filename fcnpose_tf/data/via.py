"""VGG Image Annotator (VIA 2.x) keypoint files: read projects and region-data exports, write projects.

Keypoints are VIA point regions (`shape_attributes.name == "point"`, `cx`, `cy`
in frame pixels, pixel i's centre at coordinate i). A region attribute (default
`keypoint`) names each point after a schema keypoint; in a frame where no point
carries a name, the points are taken in schema order. Missing keypoints are NaN.

The schema a file was written with (names, order, skeleton) is stored under the top-level key
`fcnpose_schema`, and again at the end of the keypoint attribute's description: VIA's Project > Save
keeps only its own keys, so after a save in VIA the description holds it (`DESCRIBED_SCHEMA`).
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Container, Sequence

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import JsonTooDeep, parse_json, read_regular_file, special_file_kind
from fcnpose_tf.keypoints import UR5, KeypointSchema

VIA_DATA_FORMAT_VERSION = "2.0.10"
SCHEMA_KEY = "fcnpose_schema"
DESCRIBED_SCHEMA = "robot keypoint; fcnpose-tf schema: "
"""What precedes the schema's JSON in the keypoint attribute's description (VIA keeps `_via_attributes` when it saves
a project, not `SCHEMA_KEY`)."""


@dataclass
class ViaFrame:
    """One annotated frame: its VIA file name, size in pixels and K x 2 (x, y) keypoints (NaN = missing).

    `size` is the image file's byte size, part of VIA's key for the frame
    (filename + size); -1 means "unknown": the writer then reads it from disk.
    `image_path` is where the reader found the image (None when written by hand).
    """

    filename: str
    width: int
    height: int
    keypoints: np.ndarray
    size: int = -1
    image_path: Path | None = field(default=None, compare=False)
    split: str | None = field(default=None, compare=False)
    """The hold-out role an earlier round gave the frame ("train" or "val", the file attribute SPLIT_ATTRIBUTE that
    `data merge` writes), or None."""

    def __post_init__(self):
        self.keypoints = np.asarray(self.keypoints, np.float64).reshape(-1, 2)

    @property
    def num_visible(self) -> int:
        """Number of annotated (finite) keypoints."""
        return int(np.isfinite(self.keypoints).all(axis=1).sum())


def _number(value: float) -> int | float:
    """A coordinate as VIA stores it: an int when whole, else a float rounded to 1/1000 px."""
    value = round(float(value), 3)
    return int(value) if value.is_integer() else value


SPLIT_ATTRIBUTE = "fcnpose_split"
"""The VIA file attribute holding a frame's hold-out role from an earlier round ("train" or "val"): `data merge`
writes it from the inputs' stored splits, and new splits keep it (`splits.holdout_split`). It shows in VIA as a
dropdown, where a person can change it."""
SPLIT_ROLES = ("train", "val")
SPLIT_ATTRIBUTE_SPEC = {"type": "dropdown", "description": "fcnpose-tf: the frame's hold-out role from an earlier "
                        "round (train or val), kept when the merged project is split", "options": {"train": "",
                        "val": ""}, "default_options": {}}
"""The attribute's declaration in a VIA project's `_via_attributes["file"]`."""


def image_key(filename: str, size: int, taken: Container[str]) -> str:
    """The key of a frame in a VIA project's `_via_img_metadata`: VIA's own, the file name and byte size run
    together (`a.png` of 11 bytes: `a.png11`), unless another frame in `taken` holds it (`a.png1` of 1 byte has
    the same): then `#2`, `#3`, ... is appended, so that no frame's entry replaces another's. VIA keeps the key
    it loads as the frame's id, so either form opens in it."""
    key = f"{filename}{size}"
    unique, n = key, 1
    while unique in taken:
        n += 1
        unique = f"{key}#{n}"
    return unique


def via_project_dict(frames: Sequence[ViaFrame], schema: KeypointSchema = UR5, attribute: str = "keypoint",
                     base_dir: str | os.PathLike | None = None, project_name: str = "fcnpose",
                     image_dir: str | os.PathLike | None = None) -> dict:
    """The VIA 2.x project (as a dict) holding `frames`' keypoints as named point regions.

    `image_dir`, the folder of the images when it is neither `base_dir` (the project file's
    folder) nor its `images/`, is stored as VIA's default path, relative to `base_dir` where given.
    Frames with size -1 get their byte size from the image file in `image_dir`, `base_dir` or
    `base_dir/images`.
    """
    default_filepath = ""
    folders = [Path(base_dir), Path(base_dir) / "images"] if base_dir is not None else []
    if image_dir is not None:
        folders.insert(0, Path(image_dir))
        default_filepath = os.path.relpath(image_dir, base_dir) if base_dir is not None else os.fspath(image_dir)
        default_filepath = "" if default_filepath == "." else default_filepath.rstrip("/") + "/"
    metadata: dict[str, dict] = {}
    seen: set[tuple[str, int]] = set()
    for frame in frames:
        if frame.keypoints.shape != (schema.num_keypoints, 2):
            raise UserError(f"frame {frame.filename!r}: expected {schema.num_keypoints} x 2 keypoints "
                             f"for schema {schema.name!r}, got {frame.keypoints.shape}")
        size = int(frame.size)
        if size < 0:
            for folder in folders:
                if (folder / frame.filename).is_file():
                    size = (folder / frame.filename).stat().st_size
                    break
        regions = [{"shape_attributes": {"name": "point", "cx": _number(x), "cy": _number(y)},
                    "region_attributes": {attribute: name}}
                   for name, (x, y) in zip(schema.keypoints, frame.keypoints)
                   if math.isfinite(x) and math.isfinite(y)]
        if (frame.filename, size) in seen:
            raise UserError(f"frame {frame.filename!r} (size {size}) appears twice")
        seen.add((frame.filename, size))
        metadata[image_key(frame.filename, size, metadata)] = {"filename": frame.filename, "size": size, "regions": regions, "file_attributes": {}}
    return {
        "_via_settings": {
            "ui": {"annotation_editor_height": 25, "annotation_editor_fontsize": 0.8,
                   "leftsidebar_width": 18,
                   "image_grid": {"img_height": 80, "rshape_fill": "none", "rshape_fill_opacity": 0.3,
                                  "rshape_stroke": "yellow", "rshape_stroke_width": 2,
                                  "show_region_shape": True, "show_image_policy": "all"},
                   "image": {"region_label": attribute, "region_color": attribute,
                             "region_label_font": "10px Sans", "on_image_annotation_editor_placement": "NEAR_REGION"}},
            "core": {"buffer_size": 18, "filepath": {}, "default_filepath": default_filepath},
            "project": {"name": project_name},
        },
        "_via_img_metadata": metadata,
        "_via_attributes": {
            "region": {attribute: {"type": "dropdown",
                                   "description": DESCRIBED_SCHEMA + json.dumps(schema.to_dict(), sort_keys=True),
                                   "options": {name: "" for name in schema.keypoints}, "default_options": {}}},
            "file": {},
        },
        "_via_data_format_version": VIA_DATA_FORMAT_VERSION,
        "_via_image_id_list": list(metadata),
        SCHEMA_KEY: schema.to_dict(),
    }


def write_via_project(path: str | os.PathLike, frames: Sequence[ViaFrame], schema: KeypointSchema = UR5,
                      attribute: str = "keypoint", force: bool = False,
                      image_dir: str | os.PathLike | None = None) -> Path:
    """Atomically write a VIA 2.x project file with `frames`' keypoints as named point regions.

    Image byte sizes (VIA's frame key) unknown in a frame (size -1) are read from
    the image file, looked up in `image_dir`, the project file's folder and its `images/`
    subfolder (-1 when not found, as VIA does for remote images). An `image_dir`
    elsewhere is stored as the project's default path (relative to the project file),
    where `read_via` looks too. Opening the file in VIA (Project > Load) shows the
    points labelled with their keypoint name.
    Raises UserError if `path` exists and not `force`.
    """
    path = Path(path)
    data = via_project_dict(frames, schema, attribute, base_dir=path.parent, project_name=path.stem,
                            image_dir=image_dir)
    return fileio.write_json(path, data, force=force)


# ----------------------------------------------------------------------------------------------- reading

logger = logging.getLogger(__name__)

EDGE_TOLERANCE_PX = 0.5
"""Points up to this far outside the frame's extent (-0.5 .. W-0.5) are clipped onto it, not refused:
VIA rounds clicks to whole pixels, so a click on the last pixel's outer half can land at W."""


@dataclass
class ViaAnnotations:
    """What `read_via` found: the kept frames, the schema, and what was dropped and why.

    `dropped` maps a reason to a frame count (frames with too few visible
    keypoints, unannotated frames, frames skipped as bad with skip_bad);
    `problems` lists one message per skipped bad frame or region.
    """

    path: Path
    schema: KeypointSchema
    frames: list[ViaFrame]
    attribute: str = "keypoint"
    min_visible: int = 1
    dropped: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    ignored_regions: int = 0

    @property
    def num_dropped(self) -> int:
        return sum(self.dropped.values())


def default_min_visible(schema: KeypointSchema) -> int:
    """Default threshold for dropping occluded frames: half the schema's keypoints, rounded up (4 of 8)."""
    return max(1, math.ceil(schema.num_keypoints / 2))


class _FrameProblem(Exception):
    """A problem with one frame or region (message already names both)."""


def _load_json(path: Path):
    kind = special_file_kind(path)
    if kind is not None:
        raise UserError(f"{path}: is {kind}, expected a VIA .json file") from None
    try:
        raw = read_regular_file(path)
    except FileNotFoundError:
        raise UserError(f"{path}: VIA file not found") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not a UTF-8 text file (byte {exc.start}); expected a VIA .json file") from None
    if not text.strip():
        raise UserError(f"{path}: empty file; expected a VIA project or region-data export (JSON)")
    try:
        return parse_json(text)
    except JsonTooDeep as exc:  # [[[[...]]]]: no VIA project is nested so deep
        raise UserError(f"{path}: not a VIA project ({exc})") from None
    except json.JSONDecodeError as exc:
        hint = " (the file looks truncated)" if exc.pos >= len(text.rstrip()) else ""
        raise UserError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}{hint}") from None


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _schema_from_attributes(data: dict, attribute: str) -> KeypointSchema | None:
    """A chain schema from the options of the region attribute, in their listed order (UR5 if they are UR5's)."""
    try:
        options = data["_via_attributes"]["region"][attribute]["options"]
    except (KeyError, TypeError):
        return None
    if not isinstance(options, dict) or not options:
        return None
    names = tuple(str(k) for k in options)
    if set(names) == set(UR5.keypoints):
        return UR5
    return KeypointSchema.chain(attribute, names)


def _json_kind(value) -> str:
    """What a JSON value is, in JSON's words: `null`, `true`, `a number`, `a string`, `a list`, `an object`."""
    if value is None or isinstance(value, bool):
        return json.dumps(value)
    if isinstance(value, (int, float)):
        return "a number"
    return {str: "a string", list: "a list", dict: "an object"}.get(type(value), type(value).__name__)


def _split_file(path: Path, data) -> tuple[dict, dict]:
    """(image metadata keyed by VIA key, settings) of a VIA 2 project or region-data export."""
    if not isinstance(data, dict):
        raise UserError(f"{path}: expected a JSON object (VIA 2 project or region-data export), "
                        f"got {_json_kind(data)}")
    if "_via_img_metadata" in data:
        metadata = data["_via_img_metadata"]
        if not isinstance(metadata, dict):
            raise UserError(f"{path}: _via_img_metadata: expected an object keyed by filename+size, "
                            f"got {_json_kind(metadata)}")
        settings = data.get("_via_settings") if isinstance(data.get("_via_settings"), dict) else {}
        return metadata, settings
    if {"project", "file", "metadata"} <= set(data) or "_via_project" in data:
        raise UserError(f"{path}: this is a VIA 3 project; open it in VIA 2.x (Project > Load) and save the "
                        "project, or export annotations as JSON, then use that file")
    metadata = {k: v for k, v in data.items() if k != SCHEMA_KEY}
    for key, meta in metadata.items():
        if not (isinstance(meta, dict) and "filename" in meta and "regions" in meta):
            raise UserError(f"{path}: entry {key!r}: not a VIA frame (expected an object with 'filename' and "
                            "'regions'); expected a VIA 2 project (_via_img_metadata) or region-data export")
    return metadata, {}


def _region_attribute_names(metadata: dict) -> set[str]:
    """Every region attribute name used in the file's regions (malformed entries are left to the parser)."""
    names: set[str] = set()
    for attributes in _region_attributes(metadata):
        names.update(str(name) for name in attributes)
    return names


def _region_attributes(metadata: dict):
    """Each region's attributes (a dict), over every frame (malformed entries are left to the parser)."""
    for meta in metadata.values():
        regions = meta.get("regions") if isinstance(meta, dict) else None
        if isinstance(regions, dict):
            regions = list(regions.values())
        for region in regions if isinstance(regions, list) else ():
            attributes = region.get("region_attributes") if isinstance(region, dict) else None
            if isinstance(attributes, dict):
                yield attributes


def _file_schema(data: object, attribute: str, path: Path | None = None) -> KeypointSchema:
    """The schema a VIA file holds: the one this package stored in it (`SCHEMA_KEY`; else, after VIA saved the
    project without that key, the one in the attribute's description while its dropdown lists the same keypoints),
    else the attribute's dropdown options, else UR5's. With `path`, a warning says when the description holds a
    schema that the dropdown overrules (edited by hand, or keypoints renamed in VIA): its name and skeleton are lost."""
    stored = data.get(SCHEMA_KEY) if isinstance(data, dict) else None
    if isinstance(stored, dict):
        return KeypointSchema.from_dict(stored)
    options = _schema_from_attributes(data, attribute)
    try:
        described = _described_schema(data, attribute)
    except UserError as exc:
        described, unread = None, str(exc)
    else:
        unread = None
    if described is not None and options is not None and set(described.keypoints) == set(options.keypoints):
        return described
    if path is not None and options is not None and (described or unread):
        why = unread or f"names other keypoints ({', '.join(described.keypoints)}) than its dropdown"
        logger.warning("%s: the fcnpose-tf schema in the %r attribute's description %s: the dropdown's keypoints are "
                       "read in their listed order, joined in a chain (%s)", path, attribute, why,
                       ", ".join(options.keypoints))
    return options or UR5


def _described_schema(data: object, attribute: str) -> KeypointSchema | None:
    """The schema `via_project_dict` wrote into the region attribute's description (`DESCRIBED_SCHEMA`), or None
    without one; UserError saying why when one is there but cannot be read."""
    try:
        description = data["_via_attributes"]["region"][attribute]["description"]
    except (KeyError, TypeError):
        return None
    if not isinstance(description, str) or DESCRIBED_SCHEMA not in description:
        return None
    try:  # the JSON object after the marker; words a user added after it are not part of it
        data, _ = json.JSONDecoder().raw_decode(description.split(DESCRIBED_SCHEMA, 1)[1].lstrip())
        return KeypointSchema.from_dict(data)
    except (ValueError, RecursionError) as exc:  # UserError among them: edited by hand
        raise UserError(f"cannot be read ({fileio.entry_problem(exc)})") from None


def _attribute_naming_keypoints(data: object, metadata: dict, present: set[str],
                                schema: KeypointSchema | None) -> str | None:
    """The one region attribute whose every value is a keypoint name (of `schema`, else of the file's stored schema,
    the attribute's dropdown options or UR5's), or None when none or several are."""
    naming = []
    for name in sorted(present):
        known = schema or _file_schema(data, name)
        values = {attributes[name] if isinstance(attributes[name], str) else None
                  for attributes in _region_attributes(metadata) if name in attributes}
        if values and values <= set(known.keypoints):
            naming.append(name)
    return naming[0] if len(naming) == 1 else None


def _image_dirs(path: Path, images_dir: str | os.PathLike | None, settings: dict) -> list[Path]:
    if images_dir is not None:
        images_dir = Path(images_dir)
        if not images_dir.is_dir():
            raise UserError(f"{images_dir}: images folder not found")
        return [images_dir]
    dirs = [path.parent, path.parent / "images"]
    core = settings.get("core") if isinstance(settings.get("core"), dict) else {}
    extra = [core.get("default_filepath")] + list(core.get("filepath") or {})
    for entry in extra:
        if isinstance(entry, str) and entry and "://" not in entry:
            d = Path(entry) if Path(entry).is_absolute() else path.parent / entry
            if d not in dirs:
                dirs.append(d)
    return dirs


def _find_image(filename: str, dirs: list[Path]) -> Path:
    if "://" in filename:
        raise _FrameProblem(f"image is a URL ({filename}); download the images and pass their folder")
    candidate = Path(filename)
    if candidate.is_absolute():
        if candidate.is_file():
            return candidate
        raise _FrameProblem(f"image file not found: {candidate}")
    for d in dirs:
        if (d / candidate).is_file():
            return d / candidate
    raise _FrameProblem("image file not found (looked in " + ", ".join(str(d) for d in dirs) + ")")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file as displayed (EXIF orientation applied), reading only its header."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        Image = None
    if Image is not None:
        try:
            with Image.open(path) as im:
                width, height = int(im.width), int(im.height)
                # EXIF orientations 5-8 rotate by 90 degrees: browsers (VIA) and OpenCV show the frame upright
                if im.getexif().get(0x0112) in (5, 6, 7, 8):
                    width, height = height, width
                return width, height
        except Exception:  # noqa: BLE001 - fall back to OpenCV, which reads more formats' bodies
            pass
    import cv2

    from fcnpose_tf.preprocess import read_image

    img = read_image(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise _FrameProblem(f"cannot read image {path} (not an image, or corrupt)")
    return int(img.shape[1]), int(img.shape[0])


def _region_label(region_attributes, attribute: str, where: str) -> str | None:
    if region_attributes is None:
        return None
    if not isinstance(region_attributes, dict):
        raise _FrameProblem(f"{where}: region_attributes must be an object, got {_json_kind(region_attributes)}")
    value = region_attributes.get(attribute)
    if value is None or value == "":
        return None
    if isinstance(value, str):
        return value.strip() or None
    if isinstance(value, dict):  # VIA checkbox attribute: {"elbow": true}
        chosen = [k for k, v in value.items() if v]
        if len(chosen) == 1:
            return str(chosen[0])
        if not chosen:
            return None
        raise _FrameProblem(f"{where}: attribute {attribute!r} has several labels ticked ({', '.join(chosen)})")
    raise _FrameProblem(f"{where}: attribute {attribute!r} must be a keypoint name, got {value!r}")


def _parse_frame(meta: dict, key: str, schema: KeypointSchema, attribute: str,
                 dirs: list[Path]) -> tuple[ViaFrame, int]:
    """One VIA entry -> (ViaFrame, number of ignored non-point regions); raises _FrameProblem."""
    filename = meta.get("filename")
    if not isinstance(filename, str) or not filename:
        raise _FrameProblem(f"entry {key!r}: 'filename' must be a non-empty string, got {filename!r}")
    label = f"frame {filename!r}"
    regions = meta.get("regions", [])
    if isinstance(regions, dict):  # VIA 1.x region exports key regions by "0", "1", ...
        regions = [regions[k] for k in sorted(regions, key=lambda k: (len(str(k)), str(k)))]
    if not isinstance(regions, list):
        raise _FrameProblem(f"{label}: 'regions' must be a list, got {_json_kind(regions)}")
    size = meta.get("size", -1)
    size = int(size) if _is_number(size) or (isinstance(size, str) and size.lstrip("-").isdigit()) else -1

    points: list[tuple[int, float, float, str | None]] = []
    ignored = 0
    for i, region in enumerate(regions):
        where = f"{label} regions[{i}]"
        if not isinstance(region, dict) or not isinstance(region.get("shape_attributes"), dict):
            raise _FrameProblem(f"{where}: expected an object with 'shape_attributes'")
        shape = region["shape_attributes"]
        if shape.get("name") != "point":
            ignored += 1
            continue
        cx, cy = shape.get("cx"), shape.get("cy")
        for axis, v in (("cx", cx), ("cy", cy)):
            if not _is_number(v):
                raise _FrameProblem(f"{where}: point {axis} must be a finite number, got {v!r}")
        points.append((i, float(cx), float(cy), _region_label(region.get("region_attributes"), attribute, where)))

    try:
        image_path = _find_image(filename, dirs)
        width, height = image_size(image_path)
    except _FrameProblem as exc:
        raise _FrameProblem(f"{label}: {exc}") from None

    keypoints = np.full((schema.num_keypoints, 2), np.nan)
    named = [p for p in points if p[3] is not None]
    if named and len(named) != len(points):
        i = next(p[0] for p in points if p[3] is None)
        raise _FrameProblem(f"{label} regions[{i}]: point has no {attribute!r} label while other points in this "
                            "frame are labelled; label every point or none (unlabelled points are taken in "
                            "schema order)")
    if not named and len(points) > schema.num_keypoints:
        raise _FrameProblem(f"{label}: {len(points)} unlabelled points but schema {schema.name!r} has "
                            f"{schema.num_keypoints} keypoints")
    first_region: dict[int, int] = {}
    for order, (i, x, y, name) in enumerate(points):
        where = f"{label} regions[{i}]"
        if name is None:
            k = order
        elif name in schema.keypoints:
            k = schema.keypoints.index(name)
        else:
            raise _FrameProblem(f"{where}: unknown keypoint label {name!r}; expected one of "
                                + ", ".join(schema.keypoints))
        if k in first_region:
            raise _FrameProblem(f"{where}: duplicate keypoint {schema.keypoints[k]!r} "
                                f"(also regions[{first_region[k]}])")
        first_region[k] = i
        t = EDGE_TOLERANCE_PX
        if not (-0.5 - t <= x <= width - 0.5 + t and -0.5 - t <= y <= height - 0.5 + t):
            raise _FrameProblem(f"{where}: point ({x:g}, {y:g}) is outside the {width}x{height} image")
        keypoints[k] = (min(max(x, -0.5), width - 0.5), min(max(y, -0.5), height - 0.5))
    file_attributes = meta.get("file_attributes")
    split = file_attributes.get(SPLIT_ATTRIBUTE) if isinstance(file_attributes, dict) else None
    return ViaFrame(filename, width, height, keypoints, size, image_path,
                    split if split in SPLIT_ROLES else None), ignored


def read_via(path: str | os.PathLike, images_dir: str | os.PathLike | None = None, *, attribute: str = "keypoint",
             schema: KeypointSchema | None = None, min_visible: int | None = None,
             skip_bad: bool = False) -> ViaAnnotations:
    """Read keypoints from a VIA 2.x project file or region-data export (JSON keyed by filename+size).

    Args:
        path: the VIA .json file.
        images_dir: folder of the images; by default the VIA file's folder, its `images/`
            subfolder and the project's default path are searched.
        attribute: region attribute naming each point's keypoint; in frames where no point
            has it, points are taken in schema order.
        schema: keypoint names and skeleton; default: the schema stored in the file by
            `write_via_project`, else the attribute's dropdown options in order (UR5 when they
            are UR5's names), else UR5.
        min_visible: frames with fewer annotated keypoints are dropped (counted, with a
            warning), as the paper drops heavily occluded frames; default half the schema's
            keypoints (4 of 8).
        skip_bad: skip frames with problems (counted in `dropped`, listed in `problems`)
            instead of raising.

    Returns:
        ViaAnnotations with the kept frames in file order.

    Raises:
        UserError: naming the file, frame and region, for invalid or truncated JSON, missing
        images, duplicate frames or keypoints, unknown labels, non-numeric coordinates or
        points outside the image (the first problem, and how many more there are).
    """
    path = Path(path)
    data = _load_json(path)
    metadata, settings = _split_file(path, data)
    present = _region_attribute_names(metadata)
    try:  # the schema the file declares (a stored one, a dropdown) refused with the file's name
        if present and attribute not in present:
            named = _attribute_naming_keypoints(data, metadata, present, schema)
            if named is not None:  # the labels under another name: read by it, not guessed in schema order
                logger.warning("%s: no region has the attribute %r (--keypoint-attr); reading the keypoint names from "
                               "%r, whose values are all keypoint names", path, attribute, named)
                attribute = named
        undeclared = schema is None and _schema_from_attributes(data, attribute) is None and not (
            isinstance(data, dict) and isinstance(data.get(SCHEMA_KEY), dict))  # UR5's by default
        if schema is None:
            schema = _file_schema(data, attribute, path)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None
    if min_visible is None:
        min_visible = default_min_visible(schema)
    if not 0 <= min_visible <= schema.num_keypoints:
        raise UserError(f"min_visible must be between 0 and {schema.num_keypoints} for schema {schema.name!r}, "
                        f"got {min_visible}")
    dirs = _image_dirs(path, images_dir, settings)
    if present and attribute not in present:  # no attribute names the points: schema order is a guess, said
        logger.warning("%s: no region has the attribute %r (--keypoint-attr), so points are taken in schema "
                       "order; the regions' attributes are: %s", path, attribute, ", ".join(sorted(present)))

    result = ViaAnnotations(path, schema, [], attribute, min_visible)
    seen: dict[str, str] = {}
    problems: list[str] = []
    too_few = f"fewer than {min_visible} visible keypoints"
    for key, meta in metadata.items():
        try:
            if not isinstance(meta, dict):
                raise _FrameProblem(f"entry {key!r}: expected an object, got {_json_kind(meta)}")
            filename = meta.get("filename")
            if isinstance(filename, str) and filename in seen:
                raise _FrameProblem(f"frame {filename!r}: duplicate frame (entries {seen[filename]!r} and {key!r})")
            frame, ignored = _parse_frame(meta, key, schema, attribute, dirs)
        except _FrameProblem as exc:
            problems.append(str(exc))
            continue
        seen[frame.filename] = key
        result.ignored_regions += ignored
        visible = frame.num_visible
        if visible < min_visible:
            reason = "no keypoints annotated" if visible == 0 else too_few
            result.dropped[reason] = result.dropped.get(reason, 0) + 1
        else:
            result.frames.append(frame)
    if problems:
        if not skip_bad:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            if not result.frames and all("image file not found" in p for p in problems):  # the images are elsewhere
                raise UserError(f"{path}: {problems[0]}{more}: none of its images is there; pass --images DIR with "
                                "the folder that holds them")
            labels = {a.get(attribute) for a in _region_attributes(metadata)}
            if undeclared and not labels & set(schema.keypoints):  # another robot's names, typed as text
                raise UserError(f"{path}: {problems[0]}{more}; the file declares no keypoints, so UR5's are expected: "
                                f"for your own robot's, make {attribute!r} a dropdown region attribute whose options "
                                "are its keypoint names in chain order (docs/data.md, \"Keypoint schema\")")
            raise UserError(f"{path}: {problems[0]}{more}; fix the file or pass --skip-bad to skip bad frames")
        result.problems = problems
        result.dropped["bad annotation or image (skipped)"] = len(problems)
        for message in problems[:5]:
            logger.warning("%s: skipped: %s", path, message)
        if len(problems) > 5:
            logger.warning("%s: skipped %d more bad frames", path, len(problems) - 5)
    for reason in (too_few, "no keypoints annotated"):
        if result.dropped.get(reason):
            logger.warning("%s: dropped %d frame(s) with %s", path, result.dropped[reason], reason)
    return result
