"""The one keypoint/skeleton drawer: palette, missing and occluded keypoints, scaling, copies, no TensorFlow."""

import subprocess
import sys

import numpy as np
import pytest

from fcnpose_tf.draw import KEYPOINT_COLOURS_BGR, draw_keypoints, keypoint_colour
from fcnpose_tf.keypoints import UR5

NAN = [np.nan, np.nan]


def _points(**where):
    """8 x 2 UR5 keypoints, NaN except the named ones."""
    kp = np.array([NAN] * UR5.num_keypoints)
    for name, xy in where.items():
        kp[UR5.keypoints.index(name)] = xy
    return kp


def test_dots_take_the_palette_colour_and_missing_keypoints_are_skipped():
    img = np.zeros((240, 320, 3), np.uint8)
    kp = _points(base=(60, 120), shoulder=(260, 120))
    out = draw_keypoints(img, kp, labels=False)
    assert tuple(out[120, 60]) == keypoint_colour(0) and tuple(out[120, 260]) == keypoint_colour(1)
    assert out[120, 160].any()  # the base-shoulder edge
    assert not out[20:100].any() and not out[140:].any()  # nothing else: no edge to a missing keypoint
    assert img.max() == 0  # a copy by default
    assert keypoint_colour(len(KEYPOINT_COLOURS_BGR)) == keypoint_colour(0)  # more keypoints: the palette repeats


def test_occluded_keypoints_are_rings():
    img = np.zeros((240, 320, 3), np.uint8)
    kp = _points(elbow=(100, 100), wrist2=(220, 100))  # not joined by an edge
    occluded = np.zeros(UR5.num_keypoints, bool)
    occluded[UR5.keypoints.index("elbow")] = True
    out = draw_keypoints(img, kp, labels=False, occluded=occluded, scale=2.0)
    assert not out[100, 100].any()  # hollow centre
    assert tuple(out[100 - 8, 100]) == keypoint_colour(2)  # the ring, radius 8 at scale 2
    assert tuple(out[100, 220]) == keypoint_colour(4)  # a filled dot


def test_point_scale_maps_keypoints_through_pixel_edges():
    img = np.zeros((200, 200, 3), np.uint8)
    out = draw_keypoints(img, _points(base=(24.5, 12.0)), labels=False, point_scale=4.0, scale=1.0)
    assert tuple(out[50, 100]) == keypoint_colour(0)  # ((24.5, 12) + 0.5) * 4 - 0.5 = (99.5, 49.5)
    assert not out[:30, :40].any()  # nothing at the unscaled position


def test_names_are_drawn_only_when_asked():
    img = np.zeros((240, 320, 3), np.uint8)
    kp = _points(base=(100, 120))
    bare = draw_keypoints(img, kp, labels=False)
    named = draw_keypoints(img, kp, labels=True)
    assert (named != bare).any() and not bare[:, 120:].any() and named[:, 108:160].any()


def test_copy_false_draws_in_place_and_non_contiguous_input_works():
    img = np.zeros((120, 160, 3), np.uint8)
    out = draw_keypoints(img, _points(base=(40, 60)), labels=False, copy=False)
    assert out is img and img[60, 40].any()
    view = np.zeros((120, 320, 3), np.uint8)[:, ::2]  # not C-contiguous (OpenCV 5 refuses to draw on it)
    assert draw_keypoints(view, _points(base=(40, 60)), labels=False)[60, 40].any()


@pytest.mark.parametrize("module", ["fcnpose_tf.draw", "fcnpose_tf.runtime.sinks"])
def test_drawer_is_pi_side_core(module):
    code = (f"import sys, {module}; bad = [m for m in ('tensorflow', 'tf_keras', 'albumentations') "
            "if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_zoom_on_maps_points_to_the_zoomed_pixels_and_the_errors_are_drawn():
    from fcnpose_tf.draw import draw_truth_and_prediction, zoom_on

    image = np.zeros((480, 640, 3), np.uint8)
    image[200, 300] = 255  # a marker at (300, 200)
    points = np.array([[280.0, 180.0], [320.0, 220.0]])
    zoomed, affine = zoom_on(image, points, side=640)
    x, y = np.array([300.0, 200.0]) @ affine[:, :2].T + affine[:, 2]
    assert max(zoomed.shape[:2]) == 640
    assert zoomed[int(round(y)), int(round(x))].max() > 0  # the marker is where the map says
    truth = np.full((8, 2), np.nan)
    predicted = np.full((8, 2), np.nan)
    truth[0], predicted[0] = (100, 100), (140, 100)
    truth[1] = (200, 200)  # missed: a cross in its ring
    picture = draw_truth_and_prediction(np.zeros((480, 640, 3), np.uint8), truth, predicted, caption="#1 a.png")
    assert picture.shape[2] == 3 and picture[:10].max() > 0  # the caption band
    assert picture.reshape(-1, 3).max(axis=1).astype(bool).mean() > 0.001


def test_wide_names_load_a_font_for_their_glyphs_once(monkeypatch, tmp_path):
    """OpenCV's own fonts draw Chinese, Japanese or Korean as `?`: the first text with such a character loads a font
    that has them (FCNPOSE_TF_FONT first, then the usual places) into OpenCV's "uni" slot, once; Latin text,
    accented or not, never looks for one."""
    import cv2

    from fcnpose_tf import draw
    from fcnpose_tf.keypoints import KeypointSchema

    font = tmp_path / "cjk.ttf"
    font.write_bytes(b"not read: setBuiltinFont is replaced")
    loaded = []
    monkeypatch.setattr(draw, "_wide_font", False)
    monkeypatch.setattr(draw, "_FONT_FILES", (str(tmp_path / "absent.ttc"),))
    monkeypatch.setattr(draw.shutil, "which", lambda name: None)  # no fontconfig
    monkeypatch.setenv(draw.FONT_ENV, str(font))
    monkeypatch.setattr(cv2.FontFace, "setBuiltinFont", lambda slot, path: loaded.append((slot, path)) or True,
                        raising=False)
    image = np.zeros((240, 320, 3), np.uint8)
    latin = KeypointSchema.chain("latin", ("Schulter", "Gelenk ä"))
    draw_keypoints(image, np.array([[80.0, 120.0], [240.0, 120.0]]), latin)
    assert loaded == []
    wide = KeypointSchema.chain("wide", ("肩", "肘"))
    for _ in range(2):
        draw_keypoints(image, np.array([[80.0, 120.0], [240.0, 120.0]]), wide)
    assert loaded == [("uni", str(font))]
    assert draw._wide_font == str(font)


def test_a_wide_name_is_drawn_with_its_glyphs_where_a_font_has_them(monkeypatch):
    """With a font for them on the machine, "肘" is drawn as itself, not as the `?` OpenCV's own fonts draw."""
    from fcnpose_tf import draw

    monkeypatch.setattr(draw, "_wide_font", False)
    if draw._wide_font_file() is None:
        pytest.skip("no font with Chinese glyphs on this machine (fonts-noto-cjk, fonts-wqy-microhei)")
    pictures = []
    for text in ("肘", "?"):
        image = np.zeros((40, 40, 3), np.uint8)
        draw.put_text(image, text, (8, 30), 0.8, (255, 255, 255))
        pictures.append(image)
    assert np.abs(pictures[0].astype(int) - pictures[1]).sum() > 0


def test_a_name_s_dark_outline_hugs_its_letters():
    """Each name is drawn in its keypoint's colour over a dark outline about a pixel wide. OpenCV 5 draws the
    Hershey constants with a TrueType font, where a thicker stroke is a wider bold font: an outline drawn that way
    ran 13 px past the end of a 22-letter name at 640 px across."""
    from fcnpose_tf.keypoints import KeypointSchema

    image = np.full((120, 640, 3), 230, np.uint8)
    schema = KeypointSchema.chain("one", ("upper wrist roll joint", "far"))
    out = draw_keypoints(image, np.array([[40.0, 60.0], [np.nan, np.nan]]), schema)
    label = out[:, 60:].astype(int)  # right of the dot, where the first free spot puts the name
    coloured = np.flatnonzero((np.abs(label - keypoint_colour(0)).sum(axis=2) < 60).any(axis=0))
    dark = np.flatnonzero((label.sum(axis=2) < 150).any(axis=0))
    assert coloured.size and dark.size
    assert abs(dark.max() - coloured.max()) <= 2 and abs(dark.min() - coloured.min()) <= 2, (coloured.max(), dark.max())
