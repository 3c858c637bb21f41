"""Look families and label conventions of the synthetic generator: held-out looks never reach pretraining,
every randomisation is seed-reproducible, kinematic labels are the projected URDF joint frames."""

import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from fcnpose_tf.data.synth import forward_kinematics, generate_dataset, render_sample, ur5_keypoints_3d
from fcnpose_tf.data.synth.frame import SENSORS
from fcnpose_tf.data.synth.looks import (ARMS, FAMILIES, LABEL_CONVENTIONS, PRETRAINING_LOOKS, check_pretraining_looks,
                                         look_family)
from fcnpose_tf.data.synth.primitives import LABEL_ROBOT
from fcnpose_tf.data.synth.robot import robot_style_for
from fcnpose_tf.data.synth.scene import _lens, light_for, random_scene
from fcnpose_tf.errors import UserError

W, H = 160, 120
TOOLS = Path(__file__).resolve().parents[1] / "tools"


def test_the_held_out_family_shares_no_component_with_a_pretraining_family():
    held = FAMILIES["heldout"]
    assert "heldout" not in PRETRAINING_LOOKS and not held.pretraining
    for name in PRETRAINING_LOOKS:
        family = FAMILIES[name]
        assert not set(family.arms) & set(held.arms)
        assert not set(family.paints) & set(held.paints)
        assert not set(family.tools) & set(held.tools)
        assert not set(family.lights) & set(held.lights)
        assert family.sensor != held.sensor
        assert family.fov_deg[1] <= held.fov_deg[0]
        assert family.corner_distortion[1] < held.corner_distortion[0]


@pytest.mark.parametrize("looks", PRETRAINING_LOOKS)
def test_pretraining_draws_never_produce_a_held_out_component(looks):
    """What each drawn robot, light and lens actually is, over many draws, not only the family's names."""
    family, held = FAMILIES[looks], FAMILIES["heldout"]
    rng = np.random.default_rng(7)
    for _ in range(300):
        style = robot_style_for(rng, family)
        assert style.arm.name not in held.arms and style.tool not in held.tools
        assert style.housing_material.rgb.max() >= 0.3 - 1e-9  # dark housings are the held-out paint
        light = light_for(rng, family)
        assert math.degrees(math.asin(light.direction[2])) < 81.0  # overhead light is held out
    for i in range(12):
        scene, _ = random_scene(np.random.default_rng(i), W, H, 0.0, looks)
        cam = scene.camera
        fov = 2 * math.degrees(math.atan(math.hypot(W - 1, H - 1) / 2 / cam.K[0, 0]))
        assert fov <= held.fov_deg[0] + 1e-6
        pull = 1 - 1 / cam.undistort_scale() if cam.k1 else 0.0
        assert pull < held.corner_distortion[0], cam.k1


def test_held_out_looks_are_refused_as_pretraining_data():
    assert check_pretraining_looks("varied").name == "varied"
    with pytest.raises(UserError, match="held out from pretraining"):
        check_pretraining_looks("heldout")
    with pytest.raises(UserError, match="unknown look family"):
        look_family("nope")


def test_the_generalists_data_command_refuses_a_held_out_family(tmp_path):
    result = subprocess.run([sys.executable, str(TOOLS / "pretrain_generalist.py"), "--work", str(tmp_path / "w"),
                             "--looks", "heldout", "--dry-run"], capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert "held out from pretraining" in result.stderr
    assert not (tmp_path / "w").exists()
    ok = subprocess.run([sys.executable, str(TOOLS / "pretrain_generalist.py"), "--work", str(tmp_path / "w"),
                         "--dry-run"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "--looks varied" in ok.stdout and "--init generalist" in ok.stdout
    mixed = subprocess.run([sys.executable, str(TOOLS / "pretrain_generalist.py"), "--work", str(tmp_path / "w"),
                            "--looks", "varied:30,classic:12", "--seed", "5", "--dry-run"], capture_output=True, text=True)
    steps = mixed.stdout.splitlines()
    assert mixed.returncode == 0 and [s.split()[3] for s in steps] == ["synth", "synth", "data", "train"], mixed.stderr
    assert "--looks varied --n 30 --seed 5 " in steps[0] and "--looks classic --n 12 --seed 2005 " in steps[1]
    assert steps[3].split("--data ")[1].startswith(str(tmp_path / "w" / "frames.json"))
    for bad in ("varied,heldout", "varied:0", "varied:x", "varied,varied"):
        refused = subprocess.run([sys.executable, str(TOOLS / "pretrain_generalist.py"), "--work", str(tmp_path / "w"),
                                  "--looks", bad, "--dry-run"], capture_output=True, text=True)
        assert refused.returncode == 2 and refused.stderr.startswith("error: "), (bad, refused.stderr)


@pytest.mark.parametrize("looks", ["varied", "heldout"])
@pytest.mark.parametrize("scene", ["workcell", "random"])
def test_every_family_is_seed_reproducible(looks, scene):
    a = render_sample(11, 3, W, H, scene=scene, looks=looks, labels="kinematic")
    b = render_sample(11, 3, W, H, scene=scene, looks=looks, labels="kinematic")
    c = render_sample(11, 4, W, H, scene=scene, looks=looks, labels="kinematic")
    assert np.array_equal(a.image, b.image) and np.array_equal(a.keypoints, b.keypoints, equal_nan=True)
    assert not np.array_equal(a.image, c.image)


def test_a_varied_set_is_identical_for_any_worker_count(tmp_path):
    one = generate_dataset(tmp_path / "one", n=4, seed=3, width=W, height=H, workers=1, progress=False,
                           scene="random", looks="varied")
    two = generate_dataset(tmp_path / "two", n=4, seed=3, width=W, height=H, workers=2, progress=False,
                           scene="random", looks="varied")
    for a, b in zip(sorted((tmp_path / "one/images").iterdir()), sorted((tmp_path / "two/images").iterdir())):
        assert a.read_bytes() == b.read_bytes()
    assert one.via_path.read_text() == two.via_path.read_text()


def test_varied_frames_draw_many_arms_tools_and_lenses():
    samples = [render_sample(5, i, W, H, scene="random", looks="varied") for i in range(24)]
    assert len({s.arm for s in samples}) >= 4
    assert len({s.tool for s in samples}) >= 4
    assert sum(s.camera.k1 != 0 for s in samples) >= 4


def _urdf_frames_projected(sample) -> np.ndarray:
    """The kinematic keypoints from the DH model, projected with OpenCV (not the generator's own camera code)."""
    arm = ARMS[sample.arm]
    frames = forward_kinematics(sample.joints, arm)
    o = frames[:, :3, 3] + (0.0, 0.0, sample.keypoints_3d[0, 2])
    z = frames[:, :3, 2]
    pts = np.array([o[0], o[1], o[2] + arm.forearm_offset * z[2], o[3] + arm.forearm_offset * z[3], o[4], o[5], o[6],
                    o[6] + sample.tool_length * z[6]])
    cam = sample.camera
    rvec, _ = cv2.Rodrigues(cam.R)
    uv, _ = cv2.projectPoints(pts, rvec, -cam.R @ cam.eye, cam.K, np.array([cam.k1, 0.0, 0.0, 0.0]))
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("looks,scene", [("heldout", "workcell"), ("heldout", "random"), ("varied", "random"),
                                         ("classic", "random")])
def test_kinematic_labels_are_the_projected_joint_frames(looks, scene):
    for i in range(4):
        s = render_sample(2, i, 320, 240, scene=scene, looks=looks, labels="kinematic")
        ok = np.isfinite(s.keypoints).all(1)
        assert ok.sum() >= 6
        np.testing.assert_allclose(s.keypoints[ok], _urdf_frames_projected(s)[ok], atol=0.5)


def test_kinematic_joint_points_lie_on_their_axes_inside_the_housings():
    rng = np.random.default_rng(0)
    for name, arm in ARMS.items():
        q = rng.uniform(-2, 2, 6)
        frames = forward_kinematics(q, arm)
        kp = ur5_keypoints_3d(q, 0.1, arm=arm, labels="kinematic")
        housing = ur5_keypoints_3d(q, 0.1, arm=arm, labels="housing")
        for k, joint in enumerate(("shoulder", "elbow", "wrist1", "wrist2", "wrist3"), start=1):
            i, (lo, hi), _, _ = arm.housings[joint]
            along = (kp[k] - frames[i, :3, 3]) @ frames[i, :3, 2]
            np.testing.assert_allclose(kp[k], frames[i, :3, 3] + along * frames[i, :3, 2], atol=1e-9)
            assert lo <= along <= hi, (name, joint, along)
        assert np.linalg.norm(kp[1:6] - housing[1:6], axis=1).max() > 0.05  # the conventions differ
        np.testing.assert_array_equal(kp[[0, 6, 7]], housing[[0, 6, 7]])


def test_distorted_frames_put_joint_keypoints_on_robot_pixels():
    """The lens resamples picture and label map together: housing-centre keypoints stay on the arm."""
    hits = total = 0
    for i in range(6):
        s = render_sample(4, i, 320, 240, scene="random", looks="heldout")
        assert s.camera.k1 < 0
        for k in range(1, 6):
            if np.isfinite(s.keypoints[k]).all() and not s.occluded[k]:
                x, y = np.round(s.keypoints[k]).astype(int)
                total += 1
                hits += s.labels[y, x] == LABEL_ROBOT
    assert total >= 20 and hits / total >= 0.9


def test_clean_sensor_has_no_noise():
    img = np.full((40, 60, 3), 0.4, np.float32)
    from fcnpose_tf.data.synth.frame import _camera_effects

    out = _camera_effects(np.random.default_rng(0), img.copy(), SENSORS["clean"])
    assert out.std() < 0.5  # a flat field stays flat
    noisy = _camera_effects(np.random.default_rng(0), img.copy(), SENSORS["varied"])
    assert noisy.shape == out.shape


def test_lens_is_drawn_only_for_families_with_distortion():
    cam = render_sample(0, 0, W, H, scene="random").camera
    assert cam.k1 == 0.0
    assert _lens(np.random.default_rng(0), cam, FAMILIES["classic"]) is cam
    distorted = _lens(np.random.default_rng(0), cam, FAMILIES["heldout"])
    assert distorted.k1 < 0 and 1.1 < distorted.undistort_scale() < 1.3


@pytest.mark.parametrize("labels", LABEL_CONVENTIONS)
def test_cli_synth_looks_and_labels(cli, tmp_path, labels):
    result = cli("synth", "--out", tmp_path / "d", "--n", "2", "--width", "96", "--height", "72",
                 "--looks", "heldout", "--labels", labels, "--workers", "1", "--quiet")
    assert result.returncode == 0, result.stderr
    assert f"heldout / {labels}" in result.stdout and "ur5e 2" in result.stdout


def test_cli_synth_unknown_looks_exit_2(cli, tmp_path):
    result = cli("synth", "--out", tmp_path / "d", "--n", "2", "--looks", "nope")
    assert result.returncode == 2 and "--looks" in result.stderr
    assert not (tmp_path / "d").exists()
