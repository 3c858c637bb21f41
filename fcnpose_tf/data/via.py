"""VGG Image Annotator (VIA 2.x) keypoint files: read projects and region-data exports, write projects.

Keypoints are VIA point regions (`shape_attributes.name == "point"`, `cx`, `cy`
in frame pixels, pixel i's centre at coordinate i). A region attribute (default
`keypoint`) names each point after a schema keypoint; in a frame where no point
carries a name, the points are taken in schema order. Missing keypoints are NaN.

The schema a file was written with is stored under the top-level key
`fcnpose_schema`, which VIA ignores, so a project round-trips through VIA.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fcnpose_tf import fileio
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema

VIA_DATA_FORMAT_VERSION = "2.0.10"
SCHEMA_KEY = "fcnpose_schema"


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


def via_project_dict(frames: Sequence[ViaFrame], schema: KeypointSchema = UR5, attribute: str = "keypoint",
                     base_dir: str | os.PathLike | None = None, project_name: str = "fcnpose") -> dict:
    """The VIA 2.x project (as a dict) holding `frames`' keypoints as named point regions.

    Frames with size -1 get their byte size from `base_dir / filename` when that file exists.
    """
    metadata: dict[str, dict] = {}
    for frame in frames:
        if frame.keypoints.shape != (schema.num_keypoints, 2):
            raise UserError(f"frame {frame.filename!r}: expected {schema.num_keypoints} x 2 keypoints "
                             f"for schema {schema.name!r}, got {frame.keypoints.shape}")
        size = int(frame.size)
        if size < 0 and base_dir is not None:
            image = Path(base_dir) / frame.filename
            if image.is_file():
                size = image.stat().st_size
        regions = [{"shape_attributes": {"name": "point", "cx": _number(x), "cy": _number(y)},
                    "region_attributes": {attribute: name}}
                   for name, (x, y) in zip(schema.keypoints, frame.keypoints)
                   if math.isfinite(x) and math.isfinite(y)]
        key = f"{frame.filename}{size}"
        if key in metadata:
            raise UserError(f"frame {frame.filename!r} (size {size}) appears twice")
        metadata[key] = {"filename": frame.filename, "size": size, "regions": regions, "file_attributes": {}}
    return {
        "_via_settings": {
            "ui": {"annotation_editor_height": 25, "annotation_editor_fontsize": 0.8,
                   "leftsidebar_width": 18,
                   "image_grid": {"img_height": 80, "rshape_fill": "none", "rshape_fill_opacity": 0.3,
                                  "rshape_stroke": "yellow", "rshape_stroke_width": 2,
                                  "show_region_shape": True, "show_image_policy": "all"},
                   "image": {"region_label": attribute, "region_color": attribute,
                             "region_label_font": "10px Sans", "on_image_annotation_editor_placement": "NEAR_REGION"}},
            "core": {"buffer_size": 18, "filepath": {}, "default_filepath": ""},
            "project": {"name": project_name},
        },
        "_via_img_metadata": metadata,
        "_via_attributes": {
            "region": {attribute: {"type": "dropdown", "description": "robot keypoint (fcnpose-tf schema "
                                                                      f"{schema.name!r})",
                                   "options": {name: "" for name in schema.keypoints}, "default_options": {}}},
            "file": {},
        },
        "_via_data_format_version": VIA_DATA_FORMAT_VERSION,
        "_via_image_id_list": list(metadata),
        SCHEMA_KEY: schema.to_dict(),
    }


def write_via_project(path: str | os.PathLike, frames: Sequence[ViaFrame], schema: KeypointSchema = UR5,
                      attribute: str = "keypoint", force: bool = False) -> Path:
    """Atomically write a VIA 2.x project file with `frames`' keypoints as named point regions.

    Image byte sizes (VIA's frame key) unknown in a frame (size -1) are read from
    the image file, looked up relative to the project file's folder. Opening the
    file in VIA (Project > Load) shows the points labelled with their keypoint name.
    Raises UserError if `path` exists and not `force`.
    """
    path = Path(path)
    data = via_project_dict(frames, schema, attribute, base_dir=path.parent, project_name=path.stem)
    return fileio.write_json(path, data, force=force)
