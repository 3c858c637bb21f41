"""Keypoints and skeleton drawn on a BGR image: one palette and one style for every picture.

Used by the synthetic-data preview (`data.synth.preview`), `data inspect`'s preview, `evaluate --pictures`
(`draw_truth_and_prediction`), `predict --draw` and the runtime's video overlay (`runtime.sinks`), so it belongs to
the Pi-side core: numpy and OpenCV only.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import unicodedata
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5, KeypointSchema

KEYPOINT_COLOURS_BGR = ((60, 60, 230), (40, 160, 250), (40, 220, 230), (60, 200, 60), (220, 200, 40),
                        (230, 110, 40), (200, 60, 200), (250, 250, 250))
"""One colour per keypoint (BGR), red to blue along the arm then magenta and white: UR5's base,
shoulder, elbow, wrist1-3, flange, tool. Schemas with more keypoints repeat it."""

_SHIFT = 4  # fractional bits of the fixed-point coordinates OpenCV draws with (1/16 px)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


FONT_ENV = "FCNPOSE_TF_FONT"
"""An environment variable naming a .ttf/.otf/.ttc font file for the characters OpenCV's own fonts lack (Chinese,
Japanese, Korean keypoint or file names)."""

_FONT_FILES = ("/usr/share/fonts/opentype/noto/NotoSansCJK-Regular.ttc",
               "/usr/share/fonts/truetype/wqy/wqy-microhei.ttc", "/usr/share/fonts/truetype/wqy/wqy-zenhei.ttc",
               "/usr/share/fonts/truetype/droid/DroidSansFallbackFull.ttf",
               "/System/Library/Fonts/PingFang.ttc", "C:/Windows/Fonts/msyh.ttc")
"""Where such a font usually is (Debian's and Raspberry Pi OS's fonts-noto-cjk, fonts-wqy-*, fonts-droid-fallback;
macOS; Windows), after `FONT_ENV` and before fontconfig's `fc-list :lang=zh`."""

_wide_font: str | None | bool = False  # the font file loaded for wide characters; None: none found; False: not sought


def _wide_font_file() -> str | None:
    """The first font file for wide characters this machine has: `FONT_ENV`'s, a usual place, or fontconfig's."""
    candidates = [os.environ.get(FONT_ENV, ""), *_FONT_FILES]
    if shutil.which("fc-list"):
        try:
            listed = subprocess.run(["fc-list", ":lang=zh", "file"], capture_output=True, text=True, timeout=10)
            candidates += sorted(line.strip().rstrip(":") for line in listed.stdout.splitlines())
        except (OSError, subprocess.SubprocessError):
            pass
    return next((path for path in candidates if path and os.path.isfile(path)
                 and cv2.FontFace.setBuiltinFont("uni", path)), None)


def _with_glyphs(text: str) -> str:
    """`text`, after loading a font for its wide characters (Chinese, Japanese, Korean: OpenCV draws them as `?`
    with its own fonts) into OpenCV's "uni" slot, once per process, if any; measure and draw text through it."""
    global _wide_font
    if _wide_font is False and not text.isascii() and any(unicodedata.east_asian_width(c) in "WF" for c in text):
        _wide_font = _wide_font_file()
    return text


def text_size(text: str, font_scale: float, thickness: int = 1) -> tuple[tuple[int, int], int]:
    """`cv2.getTextSize` in the pictures' font: ((width, height), baseline) in pixels."""
    return cv2.getTextSize(_with_glyphs(text), _FONT, font_scale, thickness)


def put_text(image_bgr: np.ndarray, text: str, org: tuple[int, int], font_scale: float,
             colour: tuple[int, int, int], outline: tuple[int, int, int] | None = None) -> None:
    """`text` drawn into the image in the pictures' font, its baseline's left end at `org`, in `colour` over an
    `outline` of about a pixel (legible on any background) when given.

    The outline is the same text shifted a pixel or two each way, not a thicker stroke: OpenCV 5 draws the Hershey
    constants with a TrueType font, where a thicker stroke is a bolder and wider font, so a halo drawn that way runs
    past the letters it should frame."""
    text = _with_glyphs(text)
    if outline is not None:
        r = max(1, round(2 * font_scale))
        for dx, dy in ((dx, dy) for dx in (-r, 0, r) for dy in (-r, 0, r) if dx or dy):
            cv2.putText(image_bgr, text, (org[0] + dx, org[1] + dy), _FONT, font_scale, outline, 1, cv2.LINE_AA)
    cv2.putText(image_bgr, text, org, _FONT, font_scale, colour, 1, cv2.LINE_AA)


def keypoint_colour(k: int) -> tuple[int, int, int]:
    """BGR colour of keypoint k."""
    return KEYPOINT_COLOURS_BGR[k % len(KEYPOINT_COLOURS_BGR)]


def _fixed(p) -> tuple[int, int]:
    return int(round(p[0] * (1 << _SHIFT))), int(round(p[1] * (1 << _SHIFT)))


def draw_keypoints(image_bgr: np.ndarray, keypoints: np.ndarray, schema: KeypointSchema = UR5, labels: bool = True,
                   occluded: np.ndarray | None = None, *, scale: float | None = None, point_scale: float = 1.0,
                   copy: bool = True) -> np.ndarray:
    """The BGR image with the skeleton, keypoint dots and (optionally) their names drawn on it.

    keypoints: K x 2 pixel coordinates (pixel-centre convention), NaN for a missing keypoint (it and
    its edges are not drawn). point_scale: the image is that many times the size of the one the
    keypoints refer to (a resized tile); they are mapped through pixel edges, (x + 0.5) * s - 0.5.
    scale: size of lines, dots and names relative to a 640 px frame (default: from the image size,
    at least 0.6). occluded: per keypoint, True draws a ring instead of a dot (hidden but annotated).
    Names are placed greedily where they overlap neither each other nor the dots, with a thin leader
    line when pushed away. copy=False draws into image_bgr itself when it is C-contiguous (OpenCV 5
    draws only on C-contiguous arrays); use the returned array either way.
    """
    out = np.ascontiguousarray(image_bgr.copy() if copy else image_bgr)
    h, w = out.shape[:2]
    if scale is None:
        scale = max(0.6, max(h, w) / 640)
    kp = (np.asarray(keypoints, np.float64) + 0.5) * point_scale - 0.5
    line = max(1, round(2 * scale))
    for a, b in schema.edges:
        if np.isfinite(kp[[a, b]]).all():
            cv2.line(out, _fixed(kp[a]), _fixed(kp[b]), (255, 255, 255), line + 2, cv2.LINE_AA, _SHIFT)
            cv2.line(out, _fixed(kp[a]), _fixed(kp[b]), keypoint_colour(a), line, cv2.LINE_AA, _SHIFT)
    r = max(2, round(4 * scale))
    visible = [k for k in range(schema.num_keypoints) if np.isfinite(kp[k]).all()]
    for k in visible:
        hollow = occluded is not None and bool(occluded[k])
        cv2.circle(out, _fixed(kp[k]), (r + 1) << _SHIFT, (0, 0, 0), -1 if not hollow else 1, cv2.LINE_AA, _SHIFT)
        cv2.circle(out, _fixed(kp[k]), r << _SHIFT, keypoint_colour(k), line if hollow else -1, cv2.LINE_AA, _SHIFT)
    if labels:
        _draw_names(out, kp, visible, schema, r, max(0.4, 0.45 * scale))
    return out


def _draw_names(out: np.ndarray, kp: np.ndarray, visible: list[int], schema: KeypointSchema, r: int,
                font_scale: float) -> None:
    """Each visible keypoint's name next to it, at the first of 32 nearby spots that is free and inside."""
    h, w = out.shape[:2]
    taken = [(kp[k, 0] - r, kp[k, 1] - r, kp[k, 0] + r, kp[k, 1] + r) for k in visible]
    for k in visible:
        name = schema.keypoints[k]
        color = keypoint_colour(k)
        (tw, th), base = text_size(name, font_scale)
        x, y = kp[k]
        best = None
        for dist in (r + 3, 3 * r + 8, 6 * r + 14, 10 * r + 22):
            for dx, dy in ((1, 0), (-1, 0), (0, -1), (0, 1), (1, -1), (-1, -1), (1, 1), (-1, 1)):
                x0 = x + dx * dist - (tw if dx < 0 else 0 if dx > 0 else tw / 2)
                y0 = y + dy * dist + (th / 2 if dy == 0 else 0 if dy > 0 else -th) - th / 2
                box = (x0 - 1, y0 - 1, x0 + tw + 1, y0 + th + base)
                if box[0] < 0 or box[1] < 0 or box[2] >= w or box[3] >= h:
                    continue
                if all(box[2] < t[0] or box[0] > t[2] or box[3] < t[1] or box[1] > t[3] for t in taken):
                    best = (box, dist)
                    break
            if best:
                break
        if best is None:
            continue  # no free spot: leave this name out rather than cover another
        box, dist = best
        taken.append(box)
        org = (int(box[0] + 1), int(box[1] + 1 + th))
        if dist > r + 3:
            anchor = (min(max(x, box[0]), box[2]), min(max(y, box[1]), box[3]))
            cv2.line(out, _fixed(kp[k]), _fixed(anchor), color, 1, cv2.LINE_AA, _SHIFT)
        put_text(out, name, org, font_scale, color, outline=(0, 0, 0))


def enlarged(image_bgr: np.ndarray, points: np.ndarray, side: int = 640) -> tuple[np.ndarray, np.ndarray]:
    """A frame smaller than `side` on its longer side, enlarged to it (the pixels' centres kept: (x + 0.5) * s -
    0.5), with its K x 2 `points` moved along, so names and captions drawn on it stay legible; a larger frame as it
    is."""
    h, w = image_bgr.shape[:2]
    s = side / max(h, w)
    if s <= 1:
        return image_bgr, np.asarray(points, np.float64)
    image = cv2.resize(image_bgr, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_LINEAR)
    return image, (np.asarray(points, np.float64) + 0.5) * s - 0.5


def zoom_on(image_bgr: np.ndarray, points: np.ndarray, side: int = 640, margin: float = 0.3
            ) -> tuple[np.ndarray, np.ndarray]:
    """The part of the image around the finite `points` (their box grown by `margin` of its larger side on each
    side, at least 32 px), resized so that its longer side is `side` pixels, and the affine map (2 x 3) from image
    to zoomed pixel-centre coordinates. The whole image when no point is finite."""
    h, w = image_bgr.shape[:2]
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = max(float((hi - lo).max()) * margin, 32.0)
        x0, y0 = (int(np.clip(np.floor(v - pad), 0, m - 1)) for v, m in zip(lo, (w, h)))
        x1, y1 = (int(np.clip(np.ceil(v + pad), 0, m - 1)) + 1 for v, m in zip(hi, (w, h)))
    else:
        x0, y0, x1, y1 = 0, 0, w, h
    s = side / max(x1 - x0, y1 - y0)
    zoomed = cv2.resize(image_bgr[y0:y1, x0:x1], (max(1, round((x1 - x0) * s)), max(1, round((y1 - y0) * s))),
                        interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
    # pixel centres: (x - x0 + 0.5) * s - 0.5
    return zoomed, np.array([[s, 0, (0.5 - x0) * s - 0.5], [0, s, (0.5 - y0) * s - 0.5]])


def draw_truth_and_prediction(image_bgr: np.ndarray, truth: np.ndarray, predicted: np.ndarray,
                              schema: KeypointSchema = UR5, caption: str | None = None, zoom: bool = True
                              ) -> np.ndarray:
    """The prediction drawn as everywhere (skeleton, dots, names) over the ground truth: a ring per annotated
    keypoint in its colour, a line from the ring to the predicted dot (the error), and a cross in the ring where
    the model found nothing. `zoom`: only the part of the frame around both (`zoom_on`), 640 px on its longer side,
    so that an error of a few pixels shows. `caption` goes in a dark band along the top."""
    truth = np.asarray(truth, np.float64)
    predicted = np.asarray(predicted, np.float64)
    if zoom:
        image_bgr, affine = zoom_on(image_bgr, np.concatenate([truth, predicted]))
        truth, predicted = (pts @ affine[:, :2].T + affine[:, 2] for pts in (truth, predicted))
    out = draw_keypoints(image_bgr, predicted, schema)
    h, w = out.shape[:2]
    scale = max(0.6, max(h, w) / 640)
    r = max(4, round(7 * scale))
    line = max(1, round(scale))
    for k in range(schema.num_keypoints):
        if not np.isfinite(truth[k]).all():
            continue
        colour = keypoint_colour(k)
        if np.isfinite(predicted[k]).all():
            cv2.line(out, _fixed(truth[k]), _fixed(predicted[k]), colour, line, cv2.LINE_AA, _SHIFT)
        else:
            for dx, dy in ((1, 1), (1, -1)):
                a, b = truth[k] - (dx * r * 0.7, dy * r * 0.7), truth[k] + (dx * r * 0.7, dy * r * 0.7)
                cv2.line(out, _fixed(a), _fixed(b), colour, line + 1, cv2.LINE_AA, _SHIFT)
        cv2.circle(out, _fixed(truth[k]), (r + 1) << _SHIFT, (0, 0, 0), line + 2, cv2.LINE_AA, _SHIFT)
        cv2.circle(out, _fixed(truth[k]), r << _SHIFT, colour, line, cv2.LINE_AA, _SHIFT)
    return with_caption(out, caption) if caption else out


def with_caption(image_bgr: np.ndarray, caption: str) -> np.ndarray:
    """`caption` in white on a dark band along the top of the image (drawn in place; the image is returned)."""
    scale = max(0.6, max(image_bgr.shape[:2]) / 640)
    font_scale = max(0.45, 0.5 * scale)
    (_, th), base = text_size(caption, font_scale)
    band = th + base + 8
    image_bgr[:band] = (image_bgr[:band] * 0.35).astype(image_bgr.dtype)
    put_text(image_bgr, caption, (6, band - base - 4), font_scale, (255, 255, 255))
    return image_bgr


def png_bytes(image_bgr: np.ndarray, where: str | os.PathLike) -> bytes:
    """The image encoded as PNG; UserError naming `where` (the file or folder it was for) if OpenCV cannot."""
    ok, png = cv2.imencode(".png", image_bgr)
    if not ok:
        raise UserError(f"{where}: cannot encode a picture as PNG")
    return png.tobytes()


def contact_sheet(images: Sequence[np.ndarray], columns: int = 3, tile_width: int | None = None) -> np.ndarray:
    """BGR images tiled row by row (`columns` a row, the last row filled with black), each resized to `tile_width`
    pixels wide when given, padded with black to the tallest, framed by a 2 px white line."""
    if not images:
        raise ValueError("no images to tile")
    tiles = []
    for image in images:
        if tile_width is not None and image.shape[1] != tile_width:
            f = tile_width / image.shape[1]
            image = cv2.resize(image, (tile_width, max(1, int(round(image.shape[0] * f)))),
                               interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)
        tiles.append(image)
    th, tw = max(t.shape[0] for t in tiles), max(t.shape[1] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, th - t.shape[0], 0, tw - t.shape[1], cv2.BORDER_CONSTANT, value=(0, 0, 0))
             for t in tiles]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.hstack([cv2.copyMakeBorder(t, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
                       for t in tiles[i:i + columns]]) for i in range(0, len(tiles), columns)]
    return np.ascontiguousarray(np.vstack(rows))
