"""Helpers of tools/pi_emulated_check.sh, run both on the x86 host and inside the emulated arm64 userland.

Needs only the standard library, numpy and OpenCV (and a TFLite interpreter for `maps`), so it runs in
the Pi-like venv that has no TensorFlow. Subcommands:

    info                      what this Python sees: machine, versions, CPU model, TensorFlow importable?
    frames DIR                write a few synthetic frames (fcnpose_tf.data.synth, else a drawn stick arm)
    maps MODEL                raw output maps of a .tflite (any shipped format) for a directory of frames
                              (or saved inputs), through the package's own preprocessing and decoding
    save-inputs NPZ OUT       the preprocessed inputs of a `maps` result, as .npy (to feed the other side)
    compare-maps A B          max abs difference of inputs and output maps of two `maps` results
    compare-keypoints A B     max keypoint distance (px) of two `fcnpose-tf run --out X.jsonl` results

Every failure prints one line `error: ...` and exits with status 2 (1 for a comparison that fails).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import os
import platform
import sys
import tempfile
from pathlib import Path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


class CheckError(Exception):
    """A problem with the inputs, reported as one line."""


# ----------------------------------------------------------------------------------------------- info

def _version(module_name: str) -> str:
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - report any import failure as text
        return f"not importable ({type(exc).__name__}: {exc})"
    return str(getattr(module, "__version__", "?"))


def _dist_version(dist: str) -> str:
    from importlib import metadata
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def cmd_info(args: argparse.Namespace) -> int:
    cpu = "?"
    with contextlib.suppress(OSError):
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        fields = {}
        for line in lines:
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
        cpu = fields.get("Model") or fields.get("model name") or fields.get("CPU part", "?")
        if "CPU part" in fields:
            cpu += f" (CPU part {fields['CPU part']}, features: {fields.get('Features', '?')})"
    tf_spec = importlib.util.find_spec("tensorflow")
    print(f"  machine:        {platform.machine()}  ({platform.platform()})")
    print(f"  python:         {platform.python_version()}  ({sys.executable})")
    print(f"  /proc/cpuinfo:  {cpu}")
    print(f"  cpus usable:    {len(os.sched_getaffinity(0))}")
    print(f"  numpy:          {_version('numpy')}")
    print(f"  opencv:         {_version('cv2')}")
    print(f"  ai-edge-litert: {_dist_version('ai-edge-litert')}")
    print(f"  fcnpose-tf:     {_dist_version('fcnpose-tf')}")
    print(f"  tensorflow:     {'importable' if tf_spec else 'absent'}")
    if args.require_no_tensorflow and tf_spec is not None:
        raise CheckError(f"tensorflow is importable here ({tf_spec.origin}); the Pi path must run without it")
    return 0


# --------------------------------------------------------------------------------------------- frames

def list_frames(frames_dir: Path) -> list[Path]:
    if not frames_dir.is_dir():
        raise CheckError(f"frames directory {frames_dir} does not exist")
    frames = sorted(p for p in frames_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not frames:
        raise CheckError(f"no image ({', '.join(IMAGE_SUFFIXES)}) in {frames_dir}")
    return frames


def cmd_frames(args: argparse.Namespace) -> int:
    """A few frames: the package's synthetic UR5 renderer when importable, else a drawn stick 'arm'."""
    import cv2
    import numpy as np

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    try:
        from fcnpose_tf.data.synth import render_frame
    except ImportError:
        render_frame = None
    for index in range(args.count):
        if render_frame is not None:
            frame = np.ascontiguousarray(render_frame(args.seed, index, args.width, args.height)[0])
        else:
            frame = _stick_arm_frame(np.random.default_rng([args.seed, index]), args.width, args.height)
        path = out / f"frame_{index:03d}.png"
        if not cv2.imwrite(str(path), frame):
            raise CheckError(f"could not write {path}")
    kind = "synthetic UR5 (fcnpose_tf.data.synth)" if render_frame else "stick-arm (no fcnpose_tf.data.synth)"
    print(f"  wrote {args.count} {kind} {args.width}x{args.height} frames to {out}")
    return 0


def _stick_arm_frame(rng, width: int, height: int):
    import cv2
    import numpy as np

    frame = np.clip(rng.integers(60, 200, 3)[None, None] + rng.normal(0, 12, (height, width, 3)), 0, 255)
    frame = np.ascontiguousarray(frame.astype(np.uint8))
    x, y = width * 0.5, height * 0.9
    angle = -math.pi / 2 + rng.uniform(-0.4, 0.4)
    points = [(x, y)]
    for length in (0.22, 0.25, 0.2, 0.08, 0.06, 0.05, 0.04):
        angle += rng.uniform(-0.9, 0.9)
        x += math.cos(angle) * length * height
        y += math.sin(angle) * length * height
        points.append((x, y))
    pts = np.round(np.array(points)).astype(np.int32)
    cv2.polylines(frame, [pts.reshape(-1, 1, 2)], False, (30, 30, 30), max(3, height // 30), cv2.LINE_AA)
    for px, py in pts:
        cv2.circle(frame, (int(px), int(py)), max(3, height // 50), (20, 160, 240), -1, cv2.LINE_AA)
    return frame


# ----------------------------------------------------------------------------------------------- maps

def load_interpreter(model: Path, threads: int, require_litert: bool):
    """(interpreter, backend name): ai_edge_litert first, then tflite_runtime, then tf.lite."""
    candidates = [("ai_edge_litert", "ai_edge_litert.interpreter")]
    if not require_litert:
        candidates += [("tflite_runtime", "tflite_runtime.interpreter"), ("tf.lite", "tensorflow.lite")]
    errors = []
    for name, module_name in candidates:
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            errors.append(f"{name}: {exc}")
            continue
        try:
            return module.Interpreter(model_path=str(model), num_threads=threads), name
        except (ValueError, RuntimeError) as exc:
            raise CheckError(f"{model} is not a loadable .tflite model ({name}: {exc})") from exc
    raise CheckError("no TFLite interpreter importable: " + "; ".join(errors))


@contextlib.contextmanager
def captured_stderr_fd():
    """Capture what C++ code writes to file descriptor 2 (LiteRT logs its delegate there), then echo it."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        box = {"text": ""}
        try:
            yield box
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            box["text"] = tmp.read().decode("utf-8", "replace")
            sys.stderr.write(box["text"])


def _runtime_model(model: Path, require_litert: bool):
    """The package's own KeypointModel for `model`: its preprocessing into the model's input type and its
    decoding are the ones `fcnpose-tf run` uses, for every format (float32 or float16 input, the int8
    file's uint8 pixel bytes, int8 maps). It loads a second interpreter: the helper invokes its own,
    whose delegate line it captures."""
    try:
        from fcnpose_tf.errors import UserError
        from fcnpose_tf.runtime.estimator import KeypointModel
    except ImportError as exc:
        raise CheckError(f"fcnpose_tf is not importable here ({exc}); install the package first") from exc
    try:
        return KeypointModel(model, 1, backend="ai_edge_litert" if require_litert else "auto")
    except UserError as exc:
        raise CheckError(str(exc)) from exc


def preprocess(runtime, frame_paths: list[Path]):
    """(the model's inputs in its own dtype, their real values as float32, the frames' H x W)."""
    import cv2
    import numpy as np

    spec = runtime.io.input
    batch = np.empty((len(frame_paths), *spec.shape[1:]), spec.dtype)
    shapes = []
    for i, path in enumerate(frame_paths):
        frame = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if frame is None:
            raise CheckError(f"could not read image {path}")
        runtime.preprocess_into(frame, batch[i])
        shapes.append(frame.shape[:2])
    return batch, real_values(batch, spec), np.array(shapes, np.int64)


def real_values(values, spec):
    """What a tensor's values stand for: (q - zero_point) * scale for a quantized one, else as float32."""
    import numpy as np

    from fcnpose_tf.postprocess import dequantize

    if spec.quantized:
        return dequantize(values, spec.scale, spec.zero_point)
    return np.asarray(values, np.float32)


def cmd_maps(args: argparse.Namespace) -> int:
    import numpy as np

    model = Path(args.model)
    if not model.is_file():
        raise CheckError(f"model {model} does not exist")
    with captured_stderr_fd() as log:
        interpreter, backend = load_interpreter(model, args.threads, args.require_litert)
        interpreter.allocate_tensors()
        # After the helper's own interpreter: LiteRT prints its delegate line once per process.
        runtime = _runtime_model(model, args.require_litert)
        spec_in, spec_out = runtime.io.input, runtime.io.output
        inp = interpreter.get_input_details()[0]
        out = interpreter.get_output_details()[0]
        frame_paths = list_frames(Path(args.frames))
        own_inputs, own_real, frame_shapes = preprocess(runtime, frame_paths)
        inputs = own_inputs if args.inputs is None else np.load(args.inputs)
        if inputs.shape[1:] != own_inputs.shape[1:] or inputs.dtype != own_inputs.dtype:
            raise CheckError(f"{args.inputs}: inputs of shape {inputs.shape} {inputs.dtype}, the model wants "
                             f"N x {' x '.join(map(str, own_inputs.shape[1:]))} {own_inputs.dtype}")
        raw = []
        for x in inputs:
            interpreter.set_tensor(inp["index"], x[None])
            interpreter.invoke()
            raw.append(interpreter.get_tensor(out["index"])[0].copy())
    xnnpack = "XNNPACK" in log["text"]
    raw = np.stack(raw)
    maps = real_values(raw, spec_out)
    tmp = Path(args.out).with_suffix(".partial.npz")
    np.savez(tmp, inputs=own_inputs, inputs_real=own_real, maps=maps, raw_maps=raw, frame_shapes=frame_shapes,
             backend=backend, xnnpack=xnnpack, output_scale=spec_out.scale, output_zero_point=spec_out.zero_point,
             output_quantized=spec_out.quantized)
    os.replace(tmp, args.out)
    size = f"{spec_in.shape[1]}x{spec_in.shape[2]}"
    print(f"  {backend}: {len(maps)} frames at {size} ({runtime.io.describe()}) -> maps {maps.shape[1:]} "
          f"(min {maps.min():.4f}, max {maps.max():.4f}); XNNPACK delegate: {'yes' if xnnpack else 'NO'}")
    if args.require_xnnpack and not xnnpack:
        raise CheckError("LiteRT did not report its XNNPACK delegate (on a Pi it does): check the emulated "
                         "/proc/cpuinfo and /sys")
    return 0


def cmd_compare_maps(args: argparse.Namespace) -> int:
    import numpy as np

    a, b = np.load(args.a), np.load(args.b)
    if a["maps"].shape != b["maps"].shape:
        raise CheckError(f"map shapes differ: {a['maps'].shape} vs {b['maps'].shape}")
    input_diff = float(np.abs(a["inputs_real"].astype(np.float64) - b["inputs_real"]).max())
    map_diff = float(np.abs(a["maps"].astype(np.float64) - b["maps"]).max())
    spread = float(a["maps"].std())
    print(f"  preprocessing (OpenCV resize, into the model's {a['inputs'].dtype} input) max abs diff: "
          f"{input_diff:.3g} (real values in [0, 1])")
    levels = ""
    if bool(a["output_quantized"]):
        step = float(a["output_scale"])
        level_diff = int(np.abs(a["raw_maps"].astype(np.int64) - b["raw_maps"]).max())
        levels = f"; {level_diff} quantization level{'s' if level_diff != 1 else ''} of {step:.3g}"
    print(f"  raw output maps max abs diff: {map_diff:.3g}{levels} (tolerance {args.tol:g}; "
          f"maps' own std {spread:.3g})")
    kp_diff = _keypoints_from_maps_diff(a, b)
    if kp_diff is not None:
        print(f"  keypoints decoded from these maps (same inputs, so the interpreter alone): "
              f"max distance {kp_diff[0]:.4g} px over {kp_diff[1]} keypoints, {kp_diff[2]} found on one side only")
    if args.result:
        Path(args.result).write_text(f"{map_diff:.3g}\n")
    if not map_diff <= args.tol:
        print(f"  maps differ by more than {args.tol:g}")
        return 1
    return 0


def _keypoints_from_maps_diff(a, b):
    """(max px, keypoints compared, found on one side only) of the two map sets decoded at frame size."""
    import numpy as np

    try:
        from fcnpose_tf.postprocess import decode
    except ImportError:
        return None
    worst, compared, one_sided = 0.0, 0, 0
    for maps_a, maps_b, shape in zip(a["maps"], b["maps"], a["frame_shapes"]):
        ka, _ = decode(maps_a, tuple(int(v) for v in shape))
        kb, _ = decode(maps_b, tuple(int(v) for v in shape))
        found_a, found_b = ~np.isnan(ka).any(axis=1), ~np.isnan(kb).any(axis=1)
        both = found_a & found_b
        one_sided += int((found_a ^ found_b).sum())
        compared += int(both.sum())
        if both.any():
            worst = max(worst, float(np.hypot(*(ka[both] - kb[both]).T).max()))
    return worst, compared, one_sided


# ------------------------------------------------------------------------------------------ keypoints

def _frame_key(record: dict, line_number: int):
    for key in ("frame", "frame_index", "index", "source_index"):
        if key in record:
            return record[key]
    return line_number


def _point(entry):
    """(x, y) or None for a missing keypoint; accepts {x, y, ...} dicts, [x, y, ...] lists and null."""
    if entry is None:
        return None
    if isinstance(entry, dict):
        x, y = entry.get("x"), entry.get("y")
    elif isinstance(entry, (list, tuple)) and len(entry) >= 2:
        x, y = entry[0], entry[1]
    else:
        raise CheckError(f"unexpected keypoint entry {entry!r}")
    if x is None or y is None or (isinstance(x, float) and math.isnan(x)):
        return None
    return float(x), float(y)


def _names(record: dict) -> list:
    points = record.get("keypoints")
    if isinstance(points, dict):
        return list(points)
    return [p.get("name", i) if isinstance(p, dict) else i for i, p in enumerate(points)]


def _points(record: dict) -> list:
    points = record.get("keypoints")
    if isinstance(points, dict):
        return [_point(v) for v in points.values()]
    if not isinstance(points, list):
        raise CheckError(f"record without a 'keypoints' list: {json.dumps(record)[:120]}")
    return [_point(p) for p in points]


def read_keypoints(path: Path) -> dict:
    if not path.is_file():
        raise CheckError(f"keypoints file {path} does not exist")
    records = {}
    for number, line in enumerate(path.read_text().splitlines()):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as exc:
            raise CheckError(f"{path}, line {number + 1}: not JSON ({exc})") from exc
        if not isinstance(record, dict) or "keypoints" not in record:
            continue  # a summary or header line
        records[_frame_key(record, number)] = record
    if not records:
        raise CheckError(f"{path} holds no keypoint record")
    return records


def cmd_compare_keypoints(args: argparse.Namespace) -> int:
    a, b = read_keypoints(Path(args.a)), read_keypoints(Path(args.b))
    problems = []
    if set(a) != set(b):
        problems.append(f"frames differ: only in {args.a}: {sorted(set(a) - set(b))[:5]}, "
                        f"only in {args.b}: {sorted(set(b) - set(a))[:5]}")
    worst, worst_where, compared, missing_both = 0.0, None, 0, 0
    for key in sorted(set(a) & set(b), key=str):
        names = _names(a[key])
        pa, pb = _points(a[key]), _points(b[key])
        if len(pa) != len(pb):
            problems.append(f"frame {key}: {len(pa)} vs {len(pb)} keypoints")
            continue
        for name, p, q in zip(names, pa, pb):
            if p is None and q is None:
                missing_both += 1
            elif p is None or q is None:
                problems.append(f"frame {key}, {name}: found on one side only ({p} vs {q})")
            else:
                d = math.hypot(p[0] - q[0], p[1] - q[1])
                compared += 1
                if worst_where is None or d > worst:
                    worst, worst_where = d, (key, name)
    frames = len(set(a) & set(b))
    print(f"  {frames} frames, {compared} keypoints found on both sides, {missing_both} missing on both")
    print(f"  max keypoint distance: {worst:.4g} px (tolerance {args.tol:g} px"
          + (f"; worst at frame {worst_where[0]}, {worst_where[1]})" if worst_where else ")"))
    if args.result:
        Path(args.result).write_text(f"{worst:.4g} {compared} {frames}\n")
    for problem in problems[:10]:
        print(f"  mismatch: {problem}")
    if compared == 0:
        print("  no keypoint was found on either side: the comparison proves nothing "
              "(use a trained model and frames that show the arm)")
        return 1
    return 1 if problems or worst > args.tol else 0


# ----------------------------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pi_check.py", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info")
    p.add_argument("--require-no-tensorflow", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("frames")
    p.add_argument("dir")
    p.add_argument("--count", type=int, default=4)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_frames)

    p = sub.add_parser("maps")
    p.add_argument("model")
    p.add_argument("--frames", required=True)
    p.add_argument("--inputs", help="feed these saved inputs (.npy) instead of this side's preprocessing")
    p.add_argument("--out", required=True, help="write inputs and maps here (.npz)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--require-litert", action="store_true", help="only ai_edge_litert, no fallback")
    p.add_argument("--require-xnnpack", action="store_true")
    p.set_defaults(func=cmd_maps)

    p = sub.add_parser("save-inputs")
    p.add_argument("npz")
    p.add_argument("out")
    p.set_defaults(func=lambda a: _save_inputs(a.npz, a.out))

    p = sub.add_parser("compare-maps")
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--tol", type=float, default=1e-4)
    p.add_argument("--result", help="write the max abs diff to this file")
    p.set_defaults(func=cmd_compare_maps)

    p = sub.add_parser("compare-keypoints")
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--tol", type=float, default=0.5)
    p.add_argument("--result", help="write 'max_px keypoints frames' to this file")
    p.set_defaults(func=cmd_compare_keypoints)

    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CheckError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _save_inputs(npz: str, out: str) -> int:
    import numpy as np

    np.save(out, np.load(npz)["inputs"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
