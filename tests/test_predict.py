"""`fcnpose-tf predict`: a model's keypoints as a VIA project, read back by `read_via`, corrected by hand.

The round trip uses a few small synthetic frames and the bundled 70 % float16 model (real
predictions); the keypoint checks use the structured model of test_runtime.py, whose keypoints
are known exactly (its `flange` is never found, so leaving out missing keypoints is checked too).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import PROCESS_TIMEOUT
from fcnpose_tf.cli import build_parser
from fcnpose_tf.data.via import read_via
from fcnpose_tf.runtime.estimator import KeypointModel
from test_runtime import RED_CYCLE, _structured_model, expected_keypoints, no_tf_env, quadrant_frame, write_video  # noqa: F401
from test_run_bench_cli import _one_line_error, _run, model_path  # noqa: F401 - fixtures

BUNDLED_P70 = Path(__file__).parents[1] / "saved_models" / "fcnpose_ur5_p70_fp16.tflite"


@pytest.fixture(scope="module")
def synth_frames(tmp_path_factory) -> Path:
    from fcnpose_tf.data.synth import generate_dataset

    out = tmp_path_factory.mktemp("synth")
    generate_dataset(out, n=3, seed=3, width=160, height=120, workers=1, progress=False)
    return out / "images"


@pytest.fixture
def quadrant_images(tmp_path) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(4):
        cv2.imwrite(str(folder / f"f{i}.png"), quadrant_frame(320, 240, RED_CYCLE[i]))
    return folder


def test_help_has_examples(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["predict", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "examples:" in text and "fcnpose-tf predict generalist --source frames/ --via frames/pre.json" in text


def test_round_trip_through_via_and_a_hand_correction(capsys, tmp_path, synth_frames):
    via = tmp_path / "labels" / "pre.json"  # elsewhere than the images: the project's default path finds them
    code, stdout, err = _run(capsys, "predict", BUNDLED_P70, "--source", synth_frames, "--via", via, "--threads", 1)
    assert code == 0, err
    default_path = json.loads(via.read_text())["_via_settings"]["core"]["default_filepath"]
    assert default_path.startswith("../") and (via.parent / default_path).resolve() == synth_frames.resolve()
    model = KeypointModel(BUNDLED_P70, 1)
    images = sorted(synth_frames.glob("*.png"))
    predicted = [model.predict(cv2.imread(str(p))).keypoints for p in images]
    annotations = read_via(via, min_visible=0)
    assert [f.filename for f in annotations.frames] == [p.name for p in images]
    for frame, want in zip(annotations.frames, predicted):
        assert (frame.width, frame.height) == (160, 120) and frame.image_path.resolve() == synth_frames / frame.filename
        np.testing.assert_allclose(frame.keypoints, want, atol=1e-3)  # VIA keeps 1/1000 px
    found = sum(int(np.isfinite(k).all(axis=1).sum()) for k in predicted)
    assert f"{len(images)} frames, {found} keypoints as points" in stdout
    steadiness = next(line for line in stdout.splitlines() if line.startswith("Steadiness:"))
    assert "px from image to image in name order (for a sequence of frames, the arm's motion" in steadiness
    assert steadiness.endswith("for stills that are not one it measures nothing)")

    # In VIA: move the first frame's elbow, delete the second frame's tool, save the project.
    data = json.loads(via.read_text())
    entries = list(data["_via_img_metadata"].values())
    elbow = next(r for r in entries[0]["regions"] if r["region_attributes"]["keypoint"] == "elbow")
    elbow["shape_attributes"].update(cx=12, cy=34.5)
    entries[1]["regions"] = [r for r in entries[1]["regions"] if r["region_attributes"]["keypoint"] != "tool"]
    via.write_text(json.dumps(data))
    edited = read_via(via, min_visible=0).frames
    assert tuple(edited[0].keypoints[2]) == (12.0, 34.5)
    assert np.isnan(edited[1].keypoints[7]).all()
    np.testing.assert_allclose(np.delete(edited[1].keypoints, 7, axis=0), np.delete(predicted[1], 7, axis=0),
                               atol=1e-3)
    np.testing.assert_allclose(edited[2].keypoints, predicted[2], atol=1e-3)  # untouched frame unchanged


def test_missing_and_unconfident_keypoints_get_no_point(capsys, tmp_path, model_path, quadrant_images):
    model = KeypointModel(model_path, 1)
    confidence = model.predict(quadrant_frame(320, 240, RED_CYCLE[0])).confidence
    cut = float(np.median(confidence[confidence > 0])) + 0.5  # some found keypoints fall below it
    via = quadrant_images / "pre.json"
    code, stdout, err = _run(capsys, "predict", model_path, "--source", quadrant_images, "--via", via,
                             "--min-confidence", cut)
    assert code == 0, err
    frames = read_via(via, min_visible=0).frames
    for i, frame in enumerate(frames):
        want = expected_keypoints(320, 240, RED_CYCLE[i])
        confident = model.predict(quadrant_frame(320, 240, RED_CYCLE[i])).confidence >= cut
        assert not confident[6]  # flange: never found
        want[~confident] = np.nan
        np.testing.assert_allclose(frame.keypoints, want, atol=1e-3)
    assert "not found" in stdout and f"below confidence {cut:g}" in stdout
    assert json.loads(via.read_text())["_via_settings"]["core"]["default_filepath"] == ""


def test_every_nth_video_frame_is_saved_beside_the_project(capsys, tmp_path, model_path):
    clip = write_video(tmp_path / "clip.avi", [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(12)])
    via = tmp_path / "out" / "clip.json"
    code, stdout, err = _run(capsys, "predict", model_path, "--source", clip, "--via", via, "--every", 3)
    assert code == 0, err
    saved = sorted(p.name for p in (tmp_path / "out" / "images").iterdir())
    assert saved == ["clip_000000.png", "clip_000003.png", "clip_000006.png", "clip_000009.png"]
    frames = read_via(via).frames
    for frame in frames:
        index = int(frame.filename[5:11])
        np.testing.assert_allclose(frame.keypoints[0], expected_keypoints(320, 240, RED_CYCLE[index % 4])[0],
                                   atol=1e-3)
    assert "4 processed" in stdout
    # The same again: the project and the saved frames are refused without --force, kept as they were.
    before = via.read_bytes()
    code, _, err = _run(capsys, "predict", model_path, "--source", clip, "--via", via, "--every", 3)
    _one_line_error(code, err, "already exists; pass --force")
    via.unlink()
    code, _, err = _run(capsys, "predict", model_path, "--source", clip, "--via", via, "--every", 3)
    _one_line_error(code, err, "clip_000000.png: already exists (frames of an earlier run); pass --force")
    assert not via.exists()
    code, _, err = _run(capsys, "predict", model_path, "--source", clip, "--via", via, "--every", 3, "--force")
    assert code == 0, err
    assert via.read_bytes() == before


def test_keras_models_predict_the_same_keypoints(capsys, tmp_path, quadrant_images):
    keras_path = tmp_path / "structured.keras"
    _structured_model().save(keras_path)
    via = tmp_path / "k.json"
    code, stdout, err = _run(capsys, "predict", keras_path, "--source", quadrant_images, "--via", via)
    assert code == 0, err
    assert "tf_keras" in stdout
    for i, frame in enumerate(read_via(via, min_visible=0).frames):
        want = expected_keypoints(320, 240, RED_CYCLE[i])
        np.testing.assert_allclose(frame.keypoints, want, atol=0.5)


@pytest.mark.parametrize("args, message", [
    (["--source", "{frames}", "--via", "out.txt"], "a VIA project is a .json file"),
    (["--source", "{frames}", "--via", "o.json", "--every", "0"], "--every must be at least 1"),
    (["--source", "{frames}", "--via", "o.json", "--min-confidence", "-1"], "--min-confidence must be at least 0"),
    (["--source", "{frames}", "--via", "o.json", "--max-frames", "0"], "--max-frames must be at least 1"),
    (["--source", "{missing}", "--via", "o.json"], "no such file or folder"),
    (["--source", "{frames}"], "the following arguments are required: --via"),
])
def test_user_errors(capsys, tmp_path, monkeypatch, model_path, quadrant_images, args, message):
    monkeypatch.chdir(tmp_path)
    args = [a.format(frames=quadrant_images, missing=tmp_path / "nope") for a in args]
    code, _, err = _run(capsys, "predict", model_path, *args)
    _one_line_error(code, err, message)
    assert not (tmp_path / "o.json").exists()


def test_missing_model_and_cameras_refused(capsys, tmp_path, model_path, quadrant_images, monkeypatch):
    code, _, err = _run(capsys, "predict", tmp_path / "nope.tflite", "--source", quadrant_images,
                        "--via", tmp_path / "o.json")
    _one_line_error(code, err, "nope.tflite: model file not found")
    opened = []
    monkeypatch.setattr("fcnpose_tf.runtime.sources.cv2.VideoCapture", lambda *a: opened.append(a))
    monkeypatch.setattr("fcnpose_tf.runtime.sources.import_picamera2", lambda: opened.append("picamera2"))
    for spec in ("0", "/dev/video0", "rtsp://127.0.0.1:8554/cam", "picamera2"):
        code, _, err = _run(capsys, "predict", model_path, "--source", spec, "--via", tmp_path / "o.json")
        _one_line_error(code, err, f"--source {spec}: predict reads image folders, images and videos; for a "
                                   "camera use `fcnpose-tf run")
    assert opened == [] and not (tmp_path / "o.json").exists()  # refused before anything was opened


def test_predict_with_a_tflite_needs_no_tensorflow(no_tf_env, model_path, quadrant_images, tmp_path):
    result = subprocess.run([sys.executable, "-m", "fcnpose_tf", "predict", str(model_path), "--source",
                             str(quadrant_images), "--via", str(tmp_path / "pre.json")], env=no_tf_env,
                            capture_output=True, text=True, timeout=PROCESS_TIMEOUT)
    assert result.returncode == 0, result.stderr
    assert len(read_via(tmp_path / "pre.json").frames) == 4


def test_sigterm_keeps_the_frames_done_as_a_project(tmp_path, model_path):
    """`kill` during predict on a video: exit 0, and every saved frame is in the VIA file (none without it)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    frames = [quadrant_frame(64, 64, RED_CYCLE[i % 4]) for i in range(4)] * 1500
    long_video = write_video(tmp_path / "long.avi", frames, fps=30)
    via = tmp_path / "out" / "pre.json"
    images = tmp_path / "out" / "images"
    proc = subprocess.Popen([sys.executable, "-m", "fcnpose_tf", "predict", str(model_path), "--source",
                             str(long_video), "--threads", "1", "--via", str(via)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2"))
    deadline = time.monotonic() + PROCESS_TIMEOUT
    while time.monotonic() < deadline and proc.poll() is None and not (images.is_dir() and any(images.iterdir())):
        time.sleep(0.02)
    assert proc.poll() is None and any(images.iterdir()), "predict did not start saving frames in time"
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=PROCESS_TIMEOUT)
    assert proc.returncode == 143, stderr  # the documented status of a stop by SIGTERM, outputs complete
    assert "terminated (SIGTERM)" in stdout
    assert stderr.splitlines()[-1] == f"terminated (SIGTERM); kept the files completed before it: {via}, {images}"
    saved = sorted(p.name for p in images.iterdir())
    named = sorted(Path(frame.filename).name for frame in read_via(via).frames)
    assert 0 < len(saved) < 6000 and saved == named


def test_draw_pictures_every_frame_written_with_its_points(capsys, tmp_path, model_path, quadrant_images):
    """--draw DIR: one PNG per frame written (a small frame enlarged to 640 px across so names stay legible, each
    found keypoint's dot in its colour where the keypoint is), a contact sheet of them; --select draws its picks only;
    a folder holding files is refused first."""
    from fcnpose_tf.draw import keypoint_colour

    pictures = tmp_path / "pictures"
    via = tmp_path / "pre.json"
    code, stdout, err = _run(capsys, "predict", model_path, "--source", quadrant_images, "--via", via,
                             "--draw", pictures, "--threads", 1)
    assert code == 0, err
    names = sorted(p.name for p in pictures.iterdir())
    assert names == ["0001_f0.png", "0002_f1.png", "0003_f2.png", "0004_f3.png", "contact_sheet.png"]
    assert f"drawn in {pictures} (4 PNG and contact_sheet.png)" in stdout
    for i, frame in enumerate(read_via(via, min_visible=0).frames):
        picture = cv2.imread(str(pictures / names[i]))
        assert picture.shape == (480, 640, 3)  # the 320 x 240 frame, twice the size
        found = [k for k in range(8) if np.isfinite(frame.keypoints[k]).all()]
        assert found
        for k in found:
            x, y = np.round((frame.keypoints[k] + 0.5) * 2 - 0.5).astype(int)
            here = [j for j in found if np.allclose(frame.keypoints[j], frame.keypoints[k])]  # dots drawn on top
            assert tuple(int(c) for c in picture[y, x]) in {keypoint_colour(j) for j in here}, (i, k)
    assert cv2.imread(str(pictures / "contact_sheet.png")).shape == (2 * 244, 3 * 324, 3)  # 4 tiles, 3 a row

    picks = tmp_path / "picks"
    code, stdout, err = _run(capsys, "predict", model_path, "--source", quadrant_images, "--via", tmp_path / "s.json",
                             "--select", 2, "--draw", picks, "--threads", 1)
    assert code == 0, err
    assert len(list(picks.glob("0*.png"))) == 2
    assert cv2.imread(str(picks / "contact_sheet.png")).shape == (244, 2 * 324, 3)

    code, stdout, err = _run(capsys, "predict", model_path, "--source", quadrant_images, "--via", tmp_path / "t.json",
                             "--draw", picks)
    assert code == 2 and "already holds files; pass --force" in err and not (tmp_path / "t.json").exists()


def test_a_stop_signal_while_predict_writes_its_project_waits_for_it(capsys, tmp_path, monkeypatch, model_path):
    """A second Ctrl-C while the project, its frames and its pictures are being written is remembered, not obeyed
    at once: a project is never kept without the frames it names (they were once deleted under it)."""
    import os
    import signal

    from fcnpose_tf.correction.prelabel import ViaPredictions

    write_sheet = ViaPredictions._write_sheet

    def write_sheet_stopped(self):
        os.kill(os.getpid(), signal.SIGINT)  # arrives after the project is written, before the contact sheet
        return write_sheet(self)

    monkeypatch.setattr(ViaPredictions, "_write_sheet", write_sheet_stopped)
    clip = write_video(tmp_path / "clip.avi", [quadrant_frame(320, 240, RED_CYCLE[i % 4]) for i in range(6)])
    via, pictures = tmp_path / "out" / "clip.json", tmp_path / "drawn"
    code, _, err = _run(capsys, "predict", model_path, "--source", clip, "--via", via, "--draw", pictures,
                        "--threads", 1)
    assert code == 130, err
    assert err.strip().splitlines()[-1].startswith("interrupted (Ctrl-C); kept the files completed before it: ")
    names = [Path(frame.filename).name for frame in read_via(via, min_visible=0).frames]
    assert len(names) == 6 and all((tmp_path / "out" / "images" / name).is_file() for name in names)
    assert (pictures / "contact_sheet.png").is_file()
