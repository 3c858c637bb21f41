"""Synthetic UR5 generator: kinematics, camera, rendering, determinism, VIA output, errors (tiny frames)."""

import json
import math

import numpy as np
import pytest

from fcnpose_tf.data import synth
from fcnpose_tf.data.synth import (Camera, forward_kinematics, generate, generate_dataset, pose_is_plausible,
                                   render_frame, render_sample, sample_joints, ur5_keypoints_3d)
from fcnpose_tf.errors import UserError
from fcnpose_tf.keypoints import UR5

W, H = 160, 120

# UR5 DH frame origins with all joints at zero (arm stretched along -x), from d1, a2, a3, d4, d5, d6.
ZERO_POSE_ORIGINS = np.array([
    [0.0, 0.0, 0.0],
    [0.0, 0.0, 0.089159],
    [-0.425, 0.0, 0.089159],
    [-0.81725, 0.0, 0.089159],
    [-0.81725, -0.10915, 0.089159],
    [-0.81725, -0.10915, 0.089159 - 0.09465],
    [-0.81725, -0.10915 - 0.0823, 0.089159 - 0.09465],
])


def test_forward_kinematics_zero_pose_gives_documented_dh_positions():
    frames = forward_kinematics(np.zeros(6))
    np.testing.assert_allclose(frames[:, :3, 3], ZERO_POSE_ORIGINS, atol=1e-12)
    np.testing.assert_allclose(frames[6, :3, 2], [0.0, -1.0, 0.0], atol=1e-12)  # flange faces -y


def test_forward_kinematics_upright_pose():
    # shoulder at -90 degrees raises the upper arm and forearm straight up
    origins = forward_kinematics([0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0])[:, :3, 3]
    np.testing.assert_allclose(origins[2], [0.0, 0.0, 0.089159 + 0.425], atol=1e-12)
    np.testing.assert_allclose(origins[3], [0.0, 0.0, 0.089159 + 0.425 + 0.39225], atol=1e-12)


def test_forward_kinematics_invariants_for_random_poses():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, 6)
        frames = forward_kinematics(q)
        o = frames[:, :3, 3]
        assert np.linalg.norm(o[2] - o[1]) == pytest.approx(0.425)
        assert np.linalg.norm(o[3] - o[2]) == pytest.approx(0.39225)
        assert np.linalg.norm(o[6] - o[5]) == pytest.approx(0.0823)
        for f in frames:  # proper rotations
            np.testing.assert_allclose(f[:3, :3] @ f[:3, :3].T, np.eye(3), atol=1e-12)
        # turning the base joint turns the whole arm about the vertical axis
        c, s = math.cos(0.7), math.sin(0.7)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        turned = forward_kinematics(q + [0.7, 0, 0, 0, 0, 0])[:, :3, 3]
        np.testing.assert_allclose(turned, o @ rz.T, atol=1e-12)


def test_keypoints_3d_lie_on_their_joint_axes():
    q = np.array([0.3, -1.2, 1.1, -1.4, -1.5, 0.2])
    frames = forward_kinematics(q)
    kp = ur5_keypoints_3d(q, tool_length=0.15, base_z=0.0)
    assert kp.shape == (UR5.num_keypoints, 3)
    np.testing.assert_allclose(kp[0], 0.0)
    for k, axis_frame in zip(range(1, 6), range(1, 6)):  # shoulder..wrist3 on the axes z1..z5
        o, z = frames[axis_frame, :3, 3], frames[axis_frame, :3, 2]
        assert np.linalg.norm(np.cross(kp[k] - o, z)) < 1e-12
    np.testing.assert_allclose(kp[6], frames[6, :3, 3])
    np.testing.assert_allclose(kp[7], frames[6, :3, 3] + 0.15 * frames[6, :3, 2])
    np.testing.assert_allclose(ur5_keypoints_3d(q, 0.15, base_z=0.5) - kp, np.tile([0, 0, 0.5], (8, 1)))


def test_sampled_poses_are_plausible_and_above_the_mount():
    rng = np.random.default_rng(2)
    for _ in range(100):
        q = sample_joints(rng, tool_length=0.15)
        assert pose_is_plausible(q, 0.15)
        assert np.all(np.abs(q) <= 2 * math.pi)
        assert ur5_keypoints_3d(q, 0.15)[1:, 2].min() > 0.0


def test_implausible_poses_are_rejected():
    assert not pose_is_plausible([0.0, 0.6, 0.0, 0.0, 0.0, 0.0])  # upper arm pointing into the floor
    assert not pose_is_plausible([0.0, -math.pi / 2, 2.9, 0.0, 0.0, 0.0])  # elbow folded onto itself


def test_camera_projection_pixel_centre_convention():
    cam = Camera.look_at([3.0, 0.0, 1.0], [0.0, 0.0, 1.0], focal=500.0, width=W, height=H)
    uv, z = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.3, 1.0], [0.0, 0.0, 1.3], [4.0, 0.0, 1.0]]))
    np.testing.assert_allclose(uv[0], [(W - 1) / 2, (H - 1) / 2])  # the target lands on the image centre
    np.testing.assert_allclose(uv[1], [(W - 1) / 2 + 50.0, (H - 1) / 2])  # looking along -x, +y is right
    assert np.linalg.det(cam.R) == pytest.approx(1.0)  # a rotation: the image is not mirrored
    np.testing.assert_allclose(uv[2], [(W - 1) / 2, (H - 1) / 2 - 50.0])  # up is up
    assert z[0] == pytest.approx(3.0) and z[3] < 0  # behind the camera
    uv2, _ = cam.scaled(2).project(np.array([[0.0, 0.3, 1.0]]))
    np.testing.assert_allclose(uv2[0], (uv[1] + 0.5) * 2 - 0.5)


@pytest.fixture(scope="module")
def samples():
    return [render_sample(0, i, W, H) for i in range(8)]


def test_rendered_keypoints_are_the_projected_kinematics(samples):
    for s in samples:
        assert s.image.shape == (H, W, 3) and s.image.dtype == np.uint8 and s.image.flags.c_contiguous
        assert s.keypoints.shape == (8, 2)
        uv, z = s.camera.project(s.keypoints_3d)
        np.testing.assert_allclose(s.keypoints_3d, ur5_keypoints_3d(s.joints, s.tool_length, s.keypoints_3d[0, 2]))
        inside = np.isfinite(s.keypoints).all(1)
        np.testing.assert_allclose(s.keypoints[inside], uv[inside])
        assert np.isnan(s.keypoints[~inside]).all()
        k = s.keypoints[inside]
        assert (k >= 0).all() and (k[:, 0] <= W - 1).all() and (k[:, 1] <= H - 1).all()
        assert (z > 0).all()


def test_joint_keypoints_are_drawn_on_the_robot(samples):
    """Where the person does not hide it, each joint centre projects onto pixels the renderer drew as robot."""
    checked = 0
    for s in samples:
        for k in range(1, 7):  # shoulder, elbow, wrist1-3, flange: inside the arm's silhouette
            if not np.isfinite(s.keypoints[k]).all() or s.occluded[k]:
                continue
            x, y = np.round(s.keypoints[k]).astype(int)
            assert s.labels[y, x] == synth.LABEL_ROBOT, (k, s.labels[y - 1:y + 2, x - 1:x + 2])
            checked += 1
    assert checked >= 30


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["workcell", "random"])
def test_the_person_hides_at_most_three_keypoints(scene):
    modes = set()
    for i in range(40):
        s = render_sample(1, i, W, H, scene=scene)
        modes.add(s.person)
        assert s.occluded.sum() <= 3
        assert s.person == "occluding" or not s.occluded.any()
        if s.person == "occluding":
            assert s.occluded.any()
    # a workcell's camera stands close to its task, leaving a co-worker little room in front of the arm
    assert modes == ({"none", "beside", "occluding"} if scene == "random" else {"none", "beside"} | modes)


def test_arm_is_framed_large_and_mostly_complete(samples):
    spans = []
    for s in samples:
        k = s.keypoints[np.isfinite(s.keypoints).all(1)]
        assert len(k) >= 6
        spans.append(max(np.ptp(k[:, 0]) / W, np.ptp(k[:, 1]) / H))
    assert 0.3 <= np.median(spans) <= 0.8


def test_render_frame_is_deterministic_per_index():
    img_a, kp_a = render_frame(5, 3, W, H)
    img_b, kp_b = render_frame(5, 3, W, H)
    img_c, _ = render_frame(5, 4, W, H)
    img_d, _ = render_frame(6, 3, W, H)
    assert np.array_equal(img_a, img_b) and np.array_equal(kp_a, kp_b, equal_nan=True)
    assert not np.array_equal(img_a, img_c) and not np.array_equal(img_a, img_d)


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_files_for_any_worker_count(tmp_path):
    a = generate(tmp_path / "a", n=4, seed=3, width=W, height=H, workers=1, progress=False)
    b = generate(tmp_path / "b", n=4, seed=3, width=W, height=H, workers=2, progress=False)
    c = generate(tmp_path / "c", n=4, seed=4, width=W, height=H, workers=1, progress=False)
    fa, fb, fc = _files(a.parent), _files(b.parent), _files(c.parent)
    assert sorted(fa) == ["images/synth_00000.png", "images/synth_00001.png", "images/synth_00002.png",
                          "images/synth_00003.png", "ur5_synth.json"]
    assert fa == fb
    assert all(fa[name] != fc[name] for name in fa)
    # a frame depends only on (seed, index): the written PNG equals the in-memory render
    import cv2

    image, _ = render_frame(3, 2, W, H)
    assert np.array_equal(cv2.imread(str(a.parent / "images/synth_00002.png")), image)


def test_via_project_has_the_keypoints_as_named_points(tmp_path):
    from fcnpose_tf.data.via import read_via

    report = generate_dataset(tmp_path / "set", n=4, seed=0, width=W, height=H, workers=1, progress=False)
    data = json.loads(report.via_path.read_text())
    meta = data["_via_img_metadata"]
    assert len(meta) == 4
    for record in report.frames:
        entry = meta[f"{record.filename}{record.size}"]
        assert entry["size"] == (tmp_path / "set/images" / record.filename).stat().st_size
        names = [r["region_attributes"]["keypoint"] for r in entry["regions"]]
        visible = [n for n, ok in zip(UR5.keypoints, np.isfinite(record.keypoints).all(1)) if ok]
        assert names == visible
        for region, (x, y) in zip(entry["regions"], record.keypoints[np.isfinite(record.keypoints).all(1)]):
            assert region["shape_attributes"]["name"] == "point"
            assert region["shape_attributes"]["cx"] == pytest.approx(x, abs=1e-3)
            assert region["shape_attributes"]["cy"] == pytest.approx(y, abs=1e-3)
    back = read_via(report.via_path, min_visible=1)
    assert [f.filename for f in back.frames] == [r.filename for r in report.frames]
    for frame, record in zip(back.frames, report.frames):
        assert (frame.width, frame.height) == (W, H)
        np.testing.assert_allclose(frame.keypoints, record.keypoints, atol=1e-3)


def test_bad_arguments_raise_user_errors(tmp_path):
    with pytest.raises(UserError, match="between 1 and"):
        generate(tmp_path / "x", n=0, width=W, height=H, progress=False)
    with pytest.raises(UserError, match="too small"):
        generate(tmp_path / "x", n=1, width=16, height=H, progress=False)
    with pytest.raises(UserError, match="workers"):
        generate(tmp_path / "x", n=1, width=W, height=H, workers=0, progress=False)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(UserError, match="not empty"):
        generate(tmp_path / "full", n=1, width=W, height=H, progress=False)
    (tmp_path / "file").write_text("")
    with pytest.raises(UserError, match="not a folder"):
        generate(tmp_path / "file", n=1, width=W, height=H, progress=False)
    with pytest.raises(UserError, match="cannot create"):
        generate(tmp_path / "file" / "sub", n=1, width=W, height=H, progress=False)


def test_force_rewrites_and_removes_stale_frames(tmp_path):
    out = tmp_path / "set"
    generate(out, n=3, seed=0, width=W, height=H, workers=1, progress=False)
    (out / "notes.txt").write_text("mine")
    (out / "ur5_synth.splits.json").write_text("{}")  # folds stored by a loader for the old frames
    generate(out, n=2, seed=1, width=W, height=H, workers=1, force=True, progress=False)
    assert sorted(p.name for p in (out / "images").iterdir()) == ["synth_00000.png", "synth_00001.png"]
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "ur5_synth.splits.json").exists()
    assert len(json.loads((out / "ur5_synth.json").read_text())["_via_img_metadata"]) == 2


def _tree(folder):
    """{relative path: SHA-256} of every file under folder."""
    import hashlib

    return {str(f.relative_to(folder)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(folder.rglob("*")) if f.is_file()}


@pytest.mark.parametrize("bad, message", [
    (dict(tight_framing=1.5), "--tight-framing must be between 0 and 1"),
    (dict(tight_framing=float("nan")), "--tight-framing must be between 0 and 1"),
    (dict(n=0), "--n must be between 1 and 1,000,000"),
    (dict(n=10**12), "--n must be between 1 and 1,000,000"),
    (dict(workers=0), "--workers must be at least 1"),
    (dict(width=8), "too small"),
    (dict(width=100000), "too large"),
    (dict(scene="workcell", motion_fps=float("inf")), "--motion needs a frame rate above 0 and at most 1000"),
    (dict(scene="lab"), "unknown scene"),
])
def test_force_with_a_bad_option_leaves_the_existing_set_untouched(tmp_path, bad, message):
    out = tmp_path / "set"
    generate(out, n=3, seed=0, width=W, height=H, workers=1, progress=False)
    (out / "ur5_synth.splits.json").write_text("{}")
    before = _tree(out)
    options = dict(n=2, seed=1, width=W, height=H, workers=1, force=True, progress=False) | bad
    with pytest.raises(UserError, match=message):
        generate(out, **options)
    assert _tree(out) == before


def test_cli_force_with_bad_tight_framing_exits_2_and_keeps_the_files(cli, tmp_path):
    out = tmp_path / "set"
    generate(out, n=2, seed=0, width=W, height=H, workers=1, progress=False)
    (out / "ur5_synth.splits.json").write_text("{}")
    before = _tree(out)
    proc = cli("synth", "--out", out, "--n", 1, "--width", W, "--height", H, "--force", "--tight-framing", "2")
    assert proc.returncode == 2
    assert "--tight-framing must be between 0 and 1" in proc.stderr and "Traceback" not in proc.stderr
    assert _tree(out) == before


def test_cli_writes_a_dataset_and_a_preview(cli, tmp_path):
    proc = cli("synth", "--out", tmp_path / "s", "--n", 2, "--width", W, "--height", H, "--workers", 1,
               "--preview", tmp_path / "p.png", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "frames" in proc.stdout and "ur5_synth.json" in proc.stdout
    assert (tmp_path / "s/images/synth_00001.png").is_file() and (tmp_path / "p.png").stat().st_size > 0


@pytest.mark.parametrize("args, message", [
    (["--n", "0"], "--n must be between 1 and"),
    (["--n", "x"], "invalid int value"),
    (["--workers", "0"], "--workers must be at least 1"),
])
def test_cli_errors_exit_2(cli, tmp_path, args, message):
    proc = cli("synth", "--out", tmp_path / "s", *args)
    assert proc.returncode == 2
    assert message in proc.stderr and "Traceback" not in proc.stderr


def test_cli_refuses_a_non_empty_folder(cli, tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "old.png").write_bytes(b"x")
    proc = cli("synth", "--out", tmp_path / "s", "--n", 1, "--width", W, "--height", H)
    assert proc.returncode == 2
    assert "not empty; pass --force" in proc.stderr and "Traceback" not in proc.stderr
    assert (tmp_path / "s" / "old.png").read_bytes() == b"x"


def test_generated_folder_loads_as_a_dataset(tmp_path):
    from fcnpose_tf.data.dataset import load_dataset

    report = generate_dataset(tmp_path / "set", n=5, seed=2, width=W, height=H, workers=1, progress=False)
    ds = load_dataset(tmp_path / "set", write_splits=False)
    assert ds.schema == UR5 and ds.names == [r.filename for r in report.frames]
    for sample, record in zip(ds.samples, report.frames):
        np.testing.assert_allclose(sample.keypoints, record.keypoints, atol=1e-3)


def test_tight_framing_option_leaves_keypoints_out_only_when_asked():
    from fcnpose_tf.data.synth import render_frame

    full = [render_frame(3, i, 160, 120)[1] for i in range(4)]
    tight = [render_frame(3, i, 160, 120, tight_framing=1.0)[1] for i in range(4)]
    assert all(not np.isnan(k).any() for k in full)
    assert any(np.isnan(k).any() for k in tight)


def _camera_key(sample):
    return np.concatenate([sample.camera.K.ravel(), sample.camera.R.ravel(), sample.camera.eye])


def test_workcell_frames_share_one_camera_and_cell_across_seeds():
    """The default scene is one fixed cell: every frame of any --seed has the same camera, mount and tool."""
    frames = [render_sample(seed, i, W, H) for seed, i in ((0, 0), (0, 1), (1, 0), (7, 3))]
    for s in frames[1:]:
        np.testing.assert_array_equal(_camera_key(s), _camera_key(frames[0]))
        assert (s.mount, s.tool, s.tool_length) == (frames[0].mount, frames[0].tool, frames[0].tool_length)
    assert len({tuple(np.round(s.joints, 6)) for s in frames}) == len(frames)  # the arm moves
    other = render_sample(0, 0, W, H, scene_seed=1)
    assert not np.array_equal(_camera_key(other), _camera_key(frames[0]))


def test_a_workcell_arm_keeps_to_its_task():
    """Every pose of a cell: base within the task's sector, elbow on the task's side, tool pointing down."""
    from fcnpose_tf.data.synth import workcell
    from fcnpose_tf.data.synth.kinematics import _wrap

    for scene_seed in (0, 2):
        task = workcell(scene_seed, W, H).task
        joints = np.array([render_sample(7, i, W, H, scene_seed=scene_seed).joints for i in range(12)])
        assert np.all(np.abs([_wrap(q - task.yaw) for q in joints[:, 0]]) <= task.half_width + 1e-9)
        assert np.all(np.sign(joints[:, 2]) == task.elbow)
        assert np.all(np.abs(joints[:, 4] + np.pi / 2) < 2.0)  # wrist 2 near -90 degrees: tool down
        assert np.ptp(joints[:, 0]) > 0.2  # but the arm does move around its sector
    assert {workcell(s, W, H).task.elbow for s in range(8)} == {-1.0, 1.0}  # both elbow sides occur


def test_random_scene_poses_are_not_tied_to_a_task():
    from fcnpose_tf.data.synth import sample_joints

    rng = np.random.default_rng(0)
    base_angles = np.array([sample_joints(rng)[0] for _ in range(200)])
    assert base_angles.min() < -2.5 and base_angles.max() > 2.5


def test_workcell_background_is_static_where_nothing_moves():
    """Pixels that show the room in two frames of one cell are the same up to sensor effects."""
    a, b = render_sample(0, 0, W, H), render_sample(0, 1, W, H)
    room = (a.labels == 0) & (b.labels == 0)
    diff = np.abs(a.image.astype(int) - b.image.astype(int)).mean(-1)[room]
    other = render_sample(0, 0, W, H, scene="random")
    diff_random = np.abs(a.image.astype(int) - other.image.astype(int)).mean(-1)[room & (other.labels == 0)]
    assert np.median(diff) < 0.5 * np.median(diff_random)


def test_random_scene_draws_a_new_camera_per_frame():
    a, b = render_sample(0, 0, W, H, scene="random"), render_sample(0, 1, W, H, scene="random")
    assert not np.array_equal(_camera_key(a), _camera_key(b))


def test_unknown_scene_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="unknown scene 'lab'"):
        render_sample(0, 0, W, H, scene="lab")
    with pytest.raises(UserError, match="unknown scene"):
        generate_dataset(tmp_path / "s", n=1, width=W, height=H, scene="lab", progress=False)


def test_cli_scene_option(cli, tmp_path):
    proc = cli("synth", "--out", tmp_path / "s", "--n", 2, "--width", W, "--height", H, "--scene", "random",
               "--scene-seed", 3, "--quiet", "--workers", 1)
    assert proc.returncode == 0, proc.stderr
    bad = cli("synth", "--out", tmp_path / "t", "--scene", "lab")
    assert bad.returncode == 2 and "invalid choice: 'lab'" in bad.stderr
