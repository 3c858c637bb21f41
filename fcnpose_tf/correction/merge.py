"""Merge VIA projects (rounds of labelling) into one project that `train --data` and `data inspect` load.

Frames are matched by file name and image: a frame annotated in two inputs (the same name, the same
image) is an error naming it and both files, unless the two annotations are identical (kept once) or
`prefer="last"` (the later file's annotation wins). Two different images that share a file name (two
sessions' `frame_0001.png`, two synthetic sets' `synth_00000.png`) are two frames: both are kept. The inputs'
keypoint schemas must be the same. Each input's images are found as `train --data` finds them (beside
the VIA file, in its `images/`, on its default path); the merged project lists their folders as VIA's
search paths (default path first, relative to the merged file), and a frame whose name would resolve to
another file there is stored with its path relative to the merged file instead. Every region and file
attribute of a kept entry is carried over unchanged (rectangles, comments and all), so nothing a person
drew is lost; frames with few keypoints are kept too (training drops them by its own --min-visible).
"""

from __future__ import annotations

import copy
import json
import filecmp
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.data import via as _via
from fcnpose_tf.data.dataset import resolve_data
from fcnpose_tf.data.splits import stored_roles
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import KeypointSchema, keypoint_difference

PREFER_CHOICES = ("error", "last")


@dataclass
class _Entry:
    source: Path
    meta: dict
    image: Path


@dataclass
class MergeResult:
    """The merged VIA project (a dict ready for `fileio.write_json`) and what the merge did."""

    project: dict
    schema: KeypointSchema
    frames_per_input: list[tuple[Path, int]]
    replaced: list[str] = field(default_factory=list)
    identical: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    image_folders: list[Path] = field(default_factory=list)
    stored_with_path: list[str] = field(default_factory=list)
    roles_kept: int = 0
    """Frames whose hold-out role (train or validation) in an input's stored splits, or in its own SPLIT_ATTRIBUTE,
    the merged project keeps (`via.SPLIT_ATTRIBUTE`): a later round never validates on an earlier round's training
    frames."""

    @property
    def num_frames(self) -> int:
        return len(self.project["_via_img_metadata"])


def same_image(a: Path, b: Path) -> bool:
    """The same image: one file (a path, a link), two files of the same bytes, or two files of the same pixels (a
    frame saved again, another PNG encoder). What `data merge`, `train --test-data` and `compress --more-frames` call
    one frame."""
    try:
        if a.resolve() == b.resolve() or os.path.samefile(a, b) or filecmp.cmp(a, b, shallow=False):
            return True
    except OSError:
        return False
    first = image_fingerprint(a)
    return first is not None and first == image_fingerprint(b)


def image_fingerprint(path: Path) -> str | None:
    """A digest of the image's decoded pixels and size (None: not readable as an image): equal for the same picture
    in two files of other bytes, so a set of them finds a frame among many at one decoding each."""
    from fcnpose_tf.preprocess import read_image

    image = read_image(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    return f"{image.shape}:{image.dtype}:{hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()}"


def _relative(folder: Path, base: Path) -> str:
    """`folder` relative to `base` (absolute when no relative path exists, as across Windows drives)."""
    try:
        return os.path.relpath(folder, base)
    except ValueError:  # pragma: no cover - different drives
        return os.fspath(folder)


def _named_by(meta: dict, found: str, attribute: str) -> dict:
    """A frame's entry whose points name their keypoints under `found` (an input read by another attribute than
    --keypoint-attr: `predict` writes `keypoint`), renamed to `attribute`: the merged project names every point one
    way, or a reader of `attribute` takes the others' points in schema order."""
    if found == attribute:
        return meta
    regions = meta.get("regions")
    for region in (regions.values() if isinstance(regions, dict) else regions if isinstance(regions, list) else ()):
        names = region.get("region_attributes") if isinstance(region, dict) else None
        if isinstance(names, dict) and found in names:
            names[attribute] = names.pop(found)
    return meta


def _regions(meta: dict) -> list[str]:
    """A frame's regions in an order of their own: the same points listed in another order are the same
    annotation (a project whose dropdown lists the keypoints in another order writes them so)."""
    regions = meta.get("regions")
    regions = list(regions.values()) if isinstance(regions, dict) else regions if isinstance(regions, list) else []
    return sorted(json.dumps(region, sort_keys=True) for region in regions)


def _schema_text(schema: KeypointSchema) -> str:
    return f"{schema.name!r} ({', '.join(schema.keypoints)})"


def merge_via_projects(inputs: Sequence[str | os.PathLike], out: str | os.PathLike, *, prefer: str = "error",
                       attribute: str = "keypoint", skip_bad: bool = False) -> MergeResult:
    """The VIA project merging `inputs` (VIA files or dataset folders, in order), to be written at `out`.

    Args:
        inputs: two or more VIA 2 projects or region-data exports (or folders holding one, as `--data`).
        out: where the merged project will be written (image paths are stored relative to its folder).
        prefer: "error": a frame annotated differently in two inputs is an error; "last": the later wins.
        attribute: the region attribute naming each point's keypoint (`--keypoint-attr`).
        skip_bad: leave out frames with bad regions or missing images (listed in `skipped`) instead of stopping.
    Raises:
        UserError: fewer than two inputs, an input given twice, keypoint schemas that differ, a frame annotated
            in two inputs (without prefer "last"), a bad frame or missing image
            (without skip_bad): naming the file and the frame.
    """
    if prefer not in PREFER_CHOICES:
        raise UserError(f"--prefer must be one of {', '.join(PREFER_CHOICES)}, got {prefer!r}")
    if len(inputs) < 2:
        raise UserError("data merge needs at least two VIA projects")
    out = Path(out)
    base = out.parent.resolve() if out.parent != Path("") else Path.cwd()
    paths: list[Path] = []
    for given in inputs:
        via_path, _ = resolve_data(given)
        if any(via_path.resolve() == p.resolve() for p in paths):
            raise UserError(f"{via_path}: given twice")
        paths.append(via_path)

    schema: KeypointSchema | None = None
    merged: dict[str, list[_Entry]] = {}  # by file name: the different images sharing it
    result = MergeResult({}, None, [])  # type: ignore[arg-type]
    attributes: dict[str, dict] = {"region": {}, "file": {}}
    renamed: set[str] = set()  # inputs' keypoint attributes other than `attribute`: their points are renamed
    for via_path in paths:
        annotations = _via.read_via(via_path, attribute=attribute, min_visible=0, skip_bad=skip_bad)
        if schema is None:
            schema = annotations.schema
        elif set(annotations.schema.keypoints) != set(schema.keypoints):
            difference = keypoint_difference(schema.keypoints, annotations.schema.keypoints, str(paths[0]), "it")
            raise UserError(f"{via_path}: keypoint schema {_schema_text(annotations.schema)} differs from "
                            f"{paths[0]}'s {_schema_text(schema)} ({difference}); only projects of the same "
                            "keypoints can be merged")
        elif annotations.schema != schema:  # the same keypoints (another order, name or skeleton): the first's
            annotations = _via.read_via(via_path, attribute=attribute, schema=schema, min_visible=0,
                                        skip_bad=skip_bad)
        result.skipped += [f"{via_path}: {message}" for message in annotations.problems]
        if annotations.attribute != attribute:
            renamed.add(annotations.attribute)
        data = _via._load_json(via_path)
        metadata, _ = _via._split_file(via_path, data)
        raw = {meta["filename"]: meta for meta in metadata.values()
               if isinstance(meta, dict) and isinstance(meta.get("filename"), str)}
        for kind in ("region", "file"):
            found = (data.get("_via_attributes") or {}).get(kind) if isinstance(data, dict) else None
            for name, spec in (found or {}).items() if isinstance(found, dict) else ():
                attributes[kind].setdefault(name, copy.deepcopy(spec))
        roles = stored_roles(via_path)
        for frame in annotations.frames:
            entry = _Entry(via_path, _named_by(copy.deepcopy(raw[frame.filename]), annotations.attribute, attribute),
                           Path(frame.image_path))
            role = frame.split or roles.get(frame.filename)
            if role is not None:
                if not isinstance(entry.meta.get("file_attributes"), dict):
                    entry.meta["file_attributes"] = {}
                entry.meta["file_attributes"][_via.SPLIT_ATTRIBUTE] = role
            named = merged.setdefault(frame.filename, [])
            earlier = next((e for e in named if same_image(e.image, entry.image)), None)
            if earlier is None:
                named.append(entry)
                continue
            if _regions(earlier.meta) == _regions(entry.meta) and \
                    earlier.meta.get("file_attributes") == entry.meta.get("file_attributes"):
                result.identical.append(frame.filename)
                continue
            if prefer != "last":
                raise UserError(f"frame {frame.filename!r}: annotated in {earlier.source} and in {via_path}; "
                                "keep one of the two (delete the frame in the other file) or pass --prefer "
                                "last to take the later file's")
            result.replaced.append(frame.filename)
            named[named.index(earlier)] = entry
        result.frames_per_input.append((via_path, len(annotations.frames)))
    assert schema is not None
    if not merged:
        raise UserError("no frames to merge: " + ", ".join(map(str, paths)) + " hold no usable frame")

    folders: list[Path] = []
    entries = [entry for named in merged.values() for entry in named]
    for entry in entries:
        folder = entry.image.parent.resolve()
        if folder not in folders:
            folders.append(folder)
    relative = [_relative(f, base) for f in folders]
    stored = [r for f, r in zip(folders, relative) if f not in (base, base / "images")]
    project = _via.via_project_dict([], schema, attribute, base_dir=base, project_name=out.stem)
    core = project["_via_settings"]["core"]
    core["default_filepath"] = (stored[0].rstrip("/") + "/") if stored else ""
    core["filepath"] = {r.rstrip("/") + "/": 1 for r in stored[1:]}
    dirs = _via._image_dirs(base / out.name, None, project["_via_settings"])
    metadata: dict[str, dict] = {}
    for entry in entries:
        meta, filename = entry.meta, entry.meta["filename"]
        try:
            found = _via._find_image(filename, dirs)
        except _via._FrameProblem:
            found = None
        if found is None or not same_image(found, entry.image):  # the name alone would find another file
            meta["filename"] = Path(_relative(entry.image.resolve(), base)).as_posix()
            result.stored_with_path.append(filename)
        size = meta.get("size", -1)
        metadata[_via.image_key(meta["filename"], size, metadata)] = meta
    result.roles_kept = sum(_via.SPLIT_ATTRIBUTE in (meta.get("file_attributes") or {}) for meta in metadata.values())
    if result.roles_kept:
        attributes["file"].setdefault(_via.SPLIT_ATTRIBUTE, copy.deepcopy(_via.SPLIT_ATTRIBUTE_SPEC))
    for kind in ("region", "file"):
        for name, spec in project["_via_attributes"][kind].items():
            attributes[kind].setdefault(name, spec)
    # the keypoint attribute as the merged schema writes it: its options and, in its description, the schema itself
    # (what survives a save in VIA), whatever the inputs' said
    attributes["region"][attribute] = project["_via_attributes"]["region"][attribute]
    for name in renamed - {attribute}:  # no point names its keypoint under it any more
        attributes["region"].pop(name, None)
    project["_via_attributes"] = attributes
    project["_via_img_metadata"] = metadata
    project["_via_image_id_list"] = list(metadata)
    result.project = project
    result.schema = schema
    result.image_folders = folders
    return result


__all__ = ["MergeResult", "PREFER_CHOICES", "image_fingerprint", "merge_via_projects", "same_image"]
