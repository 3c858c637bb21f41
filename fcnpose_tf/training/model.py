"""The FCN-Pose network, exactly as the paper's table "FCN-Pose Structure".

    conv1 pool1 conv2 pool2 conv3 pool3 conv4 pool4 conv5 pool5   (encoder)
    conv6 up1 conv7 up2 conv8 up3 conv9 up4 conv10                   (decoder)

Every Conv2D is 3x3 'same'; conv1..conv9 use ReLU, conv10 a sigmoid with one
map per keypoint plus the skeleton map. Upsampling factors are 2, 2, 2 and 4,
so an input of H x W (both multiples of 32) gives H x W maps.

What the model sees of a frame (its `preprocess.FrameView`: a crop and the input size) and what its maps stand
for (its `keypoints.KeypointSchema`) travel with it: in memory as `view_of(model)` and `schema_of(model)` (set by
`load_model`, `with_view`, `with_schema`; kept by `at_input_size`, `inference_copy` and `with_facts_of`), on disk
inside the .keras file (extra entries of its zip, `VIEW_ENTRY` and `SCHEMA_ENTRY`) or the .h5 file (root
attributes), so that one model file is enough; a model file without a view sees the whole frame, one without a
schema takes its training record's (`keypoints.named_schema`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Sequence

import tf_keras as keras

from fcnpose_tf.errors import UserError
from fcnpose_tf.fileio import entry_problem, native_name
from fcnpose_tf.keypoints import KeypointSchema, keypoint_difference, named_schema, schema_for_maps
from fcnpose_tf.metrics import conv_macs
from fcnpose_tf.preprocess import FrameView, ViewLike
from fcnpose_tf.settings import INPUT_SIZE, INPUT_SIZE_MULTIPLE, check_input_size  # noqa: F401 - re-exported

DEFAULT_WIDTHS: tuple[int, ...] = (128, 64, 32, 16, 8, 8, 16, 32, 64)
DEFAULT_INPUT_SIZE = INPUT_SIZE.default
DEFAULT_NUM_MAPS = 9
UPSAMPLE_FACTORS = (2, 2, 2, 4)
NUM_POOLS = 5
SIZE_MULTIPLE = INPUT_SIZE_MULTIPLE
SKIP_LAYERS = ("skip2", "skip_up", "skip_add")
"""The layers `build_fcn_pose(skip=True)` adds: conv2's output projected, upsampled, added before conv10."""
"""2**NUM_POOLS: an input side the five poolings divide exactly (checked by `check_input_size`)."""


VIEW_ENTRY = "fcnpose_tf_view.json"
"""The .keras zip entry (and .h5 root attribute) holding the model's `FrameView` as JSON."""
SCHEMA_ENTRY = "fcnpose_tf_schema.json"
"""The .keras zip entry (and .h5 root attribute) holding the model's `KeypointSchema` as JSON (`to_dict`)."""
_VIEW_ATTRIBUTE = "_fcnpose_tf_view"
_SCHEMA_ATTRIBUTE = "_fcnpose_tf_schema"


def input_shape_of(input_size: ViewLike) -> tuple[int, int]:
    """(height, width) of an input size.

    Args:
        input_size: S, (H, W) or a `preprocess.FrameView`.
    Returns:
        (height, width).
    Raises:
        UserError: a side that is not a multiple of 32.
    """
    if isinstance(input_size, FrameView):
        height, width = input_size.shape
    elif isinstance(input_size, (tuple, list)) and len(input_size) == 2:
        height, width = input_size
    else:
        height = width = input_size
    return check_input_size(height), check_input_size(width)


def build_fcn_pose(widths: Sequence[int] = DEFAULT_WIDTHS, input_size: ViewLike = DEFAULT_INPUT_SIZE,
                   num_maps: int = DEFAULT_NUM_MAPS, name: str = "fcn_pose", skip: bool = False) -> keras.Model:
    """Build FCN-Pose with the given widths of conv1..conv9 (conv10 has `num_maps` filters).

    With `skip`, the decoder also reads the encoder's block at half resolution: conv2's output goes through a 1x1
    convolution to conv9's width (`skip2`, linear, zero at the start, so the network computes plain FCN-Pose until
    it is trained), is upsampled by 2 (`skip_up`) and added to up4's output (`skip_add`), which conv10 reads. conv10
    then sees 2 x 2 blocks of the input instead of 4 x 4 (SKIP_LAYERS; not the paper's network).

    Args:
        widths: filters of conv1..conv9; the paper's are (128, 64, 32, 16, 8, 8, 16, 32, 64).
            Pruned models are the same network with smaller widths.
        input_size: the RGB input: S (S x S), (H, W) or a `FrameView` (its crop is kept: `view_of`); every side a
            multiple of 32.
        num_maps: output maps, keypoints + 1 skeleton map (9 for a UR5).
    Returns:
        An uncompiled tf_keras Model with layers named conv1..conv10, pool1..pool5, up1..up4.
    Raises:
        UserError: for an input size that is not a multiple of 32 or non-positive widths.
    Example:
        >>> build_fcn_pose().count_params()
        131705
    """
    height, width = input_shape_of(input_size)
    widths = tuple(int(w) for w in widths)
    if len(widths) != 9 or min(widths) < 1:
        raise UserError(f"widths must be 9 positive filter counts (conv1..conv9), got {widths}")
    if num_maps < 2:
        raise UserError(f"num_maps must be at least 2 (keypoints + skeleton), got {num_maps}")

    def conv(x, filters, index, activation="relu"):
        return keras.layers.Conv2D(filters, 3, padding="same", activation=activation, name=f"conv{index}")(x)

    inputs = keras.Input((height, width, 3), name="image")
    x = inputs
    for i in range(NUM_POOLS):
        x = conv(x, widths[i], i + 1)
        if i == 1:
            half = x  # conv2's output, before pool2: half the input's resolution
        x = keras.layers.MaxPooling2D(2, name=f"pool{i + 1}")(x)
    x = conv(x, widths[5], 6)
    for i, factor in enumerate(UPSAMPLE_FACTORS):
        x = keras.layers.UpSampling2D(factor, name=f"up{i + 1}")(x)
        if i + 7 <= 9:
            x = conv(x, widths[i + 6], i + 7)
    if skip:
        fine = keras.layers.Conv2D(widths[8], 1, kernel_initializer="zeros", name=SKIP_LAYERS[0])(half)
        fine = keras.layers.UpSampling2D(2, name=SKIP_LAYERS[1])(fine)
        x = keras.layers.Add(name=SKIP_LAYERS[2])([x, fine])
    outputs = conv(x, num_maps, 10, activation="sigmoid")
    model = keras.Model(inputs, outputs, name=name)
    return with_view(model, input_size) if isinstance(input_size, FrameView) else model


ARCHITECTURES = {"fcn-pose": False, "fcn-pose-skip": True}
"""The networks `build_fcn_pose` builds, by name (`settings.ARCHITECTURE`): whether the skip is there."""


def architecture_of(model: keras.Model) -> str:
    """Which network `model` is.

    Args:
        model: an FCN-Pose model.
    Returns:
        "fcn-pose-skip" when it has `build_fcn_pose(skip=True)`'s layers, else "fcn-pose".
    """
    names = {layer.name for layer in model.layers}
    return "fcn-pose-skip" if set(SKIP_LAYERS) <= names else "fcn-pose"


def as_architecture(model: keras.Model, architecture: str) -> keras.Model:
    """`model` as the network `architecture` names: itself when it is one already; FCN-Pose given the skip with the
    skip's 1x1 convolution at zero (the same function, weights copied by layer name, the view kept).

    Args:
        model: an FCN-Pose model.
        architecture: a name of ARCHITECTURES.
    Returns:
        The model of that network.
    Raises:
        UserError: an unknown name, or taking a trained skip away (its weights would be lost).
    """
    if architecture not in ARCHITECTURES:
        raise UserError(f"architecture must be one of {', '.join(ARCHITECTURES)}, got {architecture!r}")
    own = architecture_of(model)
    if own == architecture:
        return model
    if own == "fcn-pose-skip":
        raise UserError(f"model {model.name} is an fcn-pose-skip network: --architecture fcn-pose would drop its "
                        "trained skip (start from an fcn-pose model, or keep --architecture fcn-pose-skip)")
    widths = conv_widths(model)
    skipped = build_fcn_pose(widths[:-1], view_of(model).shape, widths[-1], name=model.name, skip=True)
    for layer in model.layers:
        if layer.weights:
            skipped.get_layer(layer.name).set_weights(layer.get_weights())
    return with_facts_of(skipped, model)


def given_view(model: keras.Model) -> FrameView | None:
    """The view `model` was given (`with_view`, `load_model` of a file that stores one).

    Args:
        model: a tf_keras model.
    Returns:
        The view, or None.
    """
    return getattr(model, _VIEW_ATTRIBUTE, None)


def view_of(model: keras.Model) -> FrameView:
    """What `model` sees of a frame.

    Args:
        model: a tf_keras model with a fixed input size.
    Returns:
        The view it was given (`given_view`), else the whole frame at its input size.
    """
    view = given_view(model)
    if view is not None:
        return view
    shape = model.input_shape
    return FrameView(int(shape[1]), int(shape[2]))


def with_view(model: keras.Model, view: ViewLike) -> keras.Model:
    """`model` with its view set.

    Args:
        model: a tf_keras model.
        view: S, (H, W) or a `preprocess.FrameView` of the model's input size.
    Returns:
        `model` (for chaining).
    Raises:
        UserError: the view's size is not the model's input.
    """
    view = FrameView.of(view)
    shape = tuple(model.input_shape[1:3])
    if shape != view.shape:
        raise UserError(f"{model.name}: a {shape[0]}x{shape[1]} input cannot take the view {view.describe()}")
    object.__setattr__(model, _VIEW_ATTRIBUTE, view)  # past Keras' attribute tracking: not a layer or weight
    return model


def given_schema(model: keras.Model) -> KeypointSchema | None:
    """The keypoint schema `model` was given (`with_schema`, `load_model`).

    Args:
        model: a tf_keras model.
    Returns:
        The schema, or None.
    """
    return getattr(model, _SCHEMA_ATTRIBUTE, None)


def schema_of(model: keras.Model) -> KeypointSchema:
    """What `model`'s maps stand for.

    Args:
        model: a tf_keras keypoint-map model.
    Returns:
        The schema it was given (`given_schema`), else `keypoints.schema_for_maps` of its output maps.
    """
    schema = given_schema(model)
    return schema if schema is not None else schema_for_maps(int(model.output_shape[-1]))


def with_schema(model: keras.Model, schema: KeypointSchema) -> keras.Model:
    """`model` with its keypoint schema set.

    Args:
        model: a tf_keras keypoint-map model.
        schema: the keypoints its maps stand for, in map order.
    Returns:
        `model` (for chaining).
    Raises:
        UserError: the schema needs another number of maps than the model has.
    """
    maps = int(model.output_shape[-1])
    if schema.num_maps != maps:
        raise UserError(f"{model.name}: {maps} output maps cannot stand for schema {schema.name!r} "
                        f"({schema.num_keypoints} keypoints + skeleton)")
    object.__setattr__(model, _SCHEMA_ATTRIBUTE, schema)  # past Keras' attribute tracking, as the view
    return model


def in_keypoint_order(model: keras.Model, schema: KeypointSchema, name: str, advice: str) -> keras.Model:
    """`model` with its keypoint maps in `schema`'s order: a model that names the same keypoints in another order
    (its file's schema, `given_schema`) gets its output layer's filters permuted (in place; the skeleton map stays
    last) and `schema`; a model that names none, or them in this order, only gets `schema`.

    Args:
        model: a keypoint-map model whose last layer is the output Conv2D.
        schema: the data's keypoints.
        name: the model's name in messages (its file).
        advice: what the refusal tells the user to do instead (the command's options).
    Returns:
        `model`.
    Raises:
        UserError: the model names other keypoints than `schema` (`keypoints.keypoint_difference` says which), or
            has another number of maps.
    """
    named = given_schema(model)
    if named is not None and named.keypoints != schema.keypoints:
        if set(named.keypoints) != set(schema.keypoints):
            difference = keypoint_difference(named.keypoints, schema.keypoints, name)
            raise UserError(f"{name}: trained for {', '.join(named.keypoints)}, but the data's schema {schema.name!r} "
                            f"has {', '.join(schema.keypoints)} ({difference}); {advice}")
        output = model.layers[-1]
        if not isinstance(output, keras.layers.Conv2D):
            raise UserError(f"{name}: its keypoints are in another order than the data's, and its last layer "
                            f"{output.name} is no Conv2D whose maps could be reordered")
        order = [named.keypoints.index(k) for k in schema.keypoints] + [schema.num_keypoints]  # skeleton last
        kernel, bias = output.get_weights()
        output.set_weights([kernel[..., order], bias[order]])
    return with_schema(model, schema)


def with_facts_of(model: keras.Model, source: keras.Model) -> keras.Model:
    """`model` with the view and the keypoint schema `source` was given (each only when given): what a rebuilt,
    cloned or pruned copy of `source` keeps.

    Args:
        model: a tf_keras model of `source`'s input size and maps.
        source: the model whose facts it takes.
    Returns:
        `model` (for chaining).
    """
    if (view := given_view(source)) is not None:
        with_view(model, view)
    if (schema := given_schema(source)) is not None:
        with_schema(model, schema)
    return model


def _read_entry(path, entry: str) -> str | None:
    """The text of a .keras zip entry or .h5 root attribute, None when the file has none."""
    import zipfile
    from pathlib import Path

    if Path(path).suffix == ".keras":
        with zipfile.ZipFile(path) as archive:
            if entry not in archive.namelist():
                return None
            return archive.read(entry).decode("utf-8")
    import h5py

    with h5py.File(native_name(path), "r") as h5:
        value = h5.attrs.get(entry)
    if value is None:
        return None
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


def read_stored_view(path) -> FrameView | None:
    """The view stored in a .keras or .h5 model file.

    Args:
        path: the model file.
    Returns:
        The view, or None (none stored: the whole frame).
    Raises:
        UserError: a stored view that cannot be read.
    """
    import zipfile

    try:
        text = _read_entry(path, VIEW_ENTRY)
        return None if text is None else FrameView.from_json(json.loads(text))
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, RecursionError) as exc:
        raise UserError(f"{path}: its stored frame view cannot be read ({entry_problem(exc)})") from exc


def read_stored_schema(path, num_maps: int) -> KeypointSchema | None:
    """The keypoint schema a .keras or .h5 model file names (`keypoints.named_schema`: stored, else recorded).

    Args:
        path: the model file.
        num_maps: the model's output maps.
    Returns:
        The schema, or None.
    Raises:
        UserError: a stored schema that cannot be read or does not fit the maps.
    """
    import zipfile

    try:
        text = _read_entry(path, SCHEMA_ENTRY)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path}: its stored keypoint schema cannot be read ({entry_problem(exc)})") from exc
    return named_schema(num_maps, text, path)


def _store_entries(path, entries: dict[str, str]) -> None:
    """Add text entries (zip entries of a .keras, root attributes of an .h5) to a model file just written (before
    it is renamed into place)."""
    import zipfile
    from pathlib import Path

    if Path(path).suffix == ".keras":
        with zipfile.ZipFile(path, "a") as archive:
            for name, text in entries.items():
                archive.writestr(name, text)
    else:
        import h5py

        with h5py.File(path, "a") as h5:
            for name, text in entries.items():
                h5.attrs[name] = text


@dataclass(frozen=True)
class LayerRow:
    """One line of the paper-style model table."""

    name: str
    kind: str
    output_shape: tuple[int, ...]
    params: int
    macs: int


def describe(model: keras.Model) -> list[LayerRow]:
    """Layer table of a model: name, type, output shape (without batch), parameters and conv MACs.

    Args:
        model: a tf_keras model.
    Returns:
        One row per layer.
    """
    rows = []
    for layer in model.layers:
        shape = layer.output_shape
        if isinstance(shape, list):
            shape = shape[0]
        shape = tuple(int(d) for d in shape[1:] if d is not None)
        macs = 0
        if isinstance(layer, keras.layers.Conv2D):
            kh, kw, cin, cout = layer.kernel.shape
            macs = conv_macs(shape[0], shape[1], int(kh), int(kw), int(cin), int(cout))
        rows.append(LayerRow(layer.name, type(layer).__name__, shape, layer.count_params(), macs))
    return rows


def conv_widths(model: keras.Model) -> tuple[int, ...]:
    """Filter counts of conv1..conv10 in order (the last is the number of output maps; the skip's 1x1 convolution,
    which follows conv9's width, is not one of them).

    Args:
        model: an FCN-Pose model.
    Returns:
        The widths.
    """
    return tuple(int(layer.filters) for layer in model.layers
                 if isinstance(layer, keras.layers.Conv2D) and layer.name not in SKIP_LAYERS)


def at_input_size(model: keras.Model, input_size: ViewLike) -> keras.Model:
    """`model` (FCN-Pose, or any fully convolutional chain) at another input size with the same layers and
    weights. The convolutions do not depend on the input size: a model trained at 224 runs, and retrains, at 192,
    320 or 224 x 288.

    Args:
        model: a tf_keras model.
        input_size: S, (H, W) (the model's own crop kept) or a `preprocess.FrameView` (its crop taken).
    Returns:
        The model at that size; `model` itself when already so.
    Raises:
        UserError: a side that is not a multiple of 32.
    """
    height, width = input_shape_of(input_size)
    view = input_size if isinstance(input_size, FrameView) else view_of(model).with_input(height, width)
    if tuple(model.input_shape[1:3]) == (height, width):
        return with_view(model, view)
    inputs = keras.Input((height, width, model.input_shape[-1]), name=model.input_names[0])
    resized = keras.models.clone_model(model, input_tensors=inputs)
    resized.set_weights(model.get_weights())
    if (schema := given_schema(model)) is not None:
        with_schema(resized, schema)
    return with_view(resized, view)


def at_input_height(model: keras.Model, height: int) -> keras.Model:
    """`model` at input height `height`, its width following at the same aspect (a multiple of 32), its crop kept:
    `compress --input-size` and `export --input-size` for a model whose input is H x W.

    Args:
        model: a tf_keras FCN-Pose.
        height: the new input height, a multiple of 32.
    Returns:
        The model at that size (`at_input_size`).
    Raises:
        UserError: a height that is not a multiple of 32.
    """
    view = view_of(model)
    width = max(32, int(round(height * view.width / view.height / 32)) * 32)
    return at_input_size(model, (height, width))


def chain_layers(model: keras.Model, purpose: str, error: type[UserError] = UserError,
                 check_layer=None) -> list[keras.layers.Layer]:
    """The model's layers after its input, checked to form one unbranched single-input chain.

    Args:
        model: a tf_keras model.
        purpose: completes the error messages ("filter pruning handles ...").
        error: the UserError subclass raised for a model that is not such a chain.
        check_layer: if given, vets every layer before the wiring is checked (so an unsupported layer is named
            first).
    Returns:
        The layers, in order.
    Raises:
        UserError: (`error`) a model that is not one built single-input, single-output chain.
    """
    if not isinstance(model, keras.Model):
        raise error(f"expected a tf_keras Model, got {type(model).__name__} "
                    "(models must be built with `import tf_keras as keras`)")
    if not model.built or not getattr(model, "inputs", None):
        raise error(f"model {model.name} is not built: give it an input shape (keras.Input) first")
    if len(model.inputs) != 1 or len(model.outputs) != 1:
        raise error(f"model {model.name} has {len(model.inputs)} inputs and {len(model.outputs)} outputs; "
                    f"{purpose} handles a single-input, single-output chain")
    layers = [layer for layer in model.layers if not isinstance(layer, keras.layers.InputLayer)]
    for layer in layers if check_layer else ():
        check_layer(layer)
    if not isinstance(model, keras.Sequential):
        # A functional model: every layer must read exactly the previous layer's only output.
        config = model.get_config()
        previous = config["input_layers"][0][0]
        for entry in config["layers"]:
            if entry["class_name"] == "InputLayer":
                continue
            nodes = entry["inbound_nodes"]
            sources = [inbound[0] for node in nodes for inbound in node]
            if len(nodes) != 1 or sources != [previous]:
                raise error(f"layer {entry['name']} reads {', '.join(sources) or 'nothing'} instead of only "
                            f"{previous}: {purpose} handles a plain chain without branches or skip connections")
            previous = entry["name"]
        if [out[0] for out in config["output_layers"]] != [previous]:
            raise error(f"model {model.name}: its output is not the end of its layer chain ({previous})")
    return layers


def h5_bytes(model: keras.Model) -> bytes:
    """`model` as it is (architecture, weights, any optimizer state) as the bytes of an .h5 file, made in memory.

    HDF5 writing straight to a file kills the process (h5py segfaults closing it) when the disk fills
    mid-write; written by Python instead, a full disk is a plain OSError (`fileio.atomic_path` names it).

    Args:
        model: a tf_keras model.
    Returns:
        The file's bytes.
    """
    import io

    import h5py

    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as h5:
        model.save(h5, save_format="h5")
    return buffer.getvalue()


def inference_copy(model: keras.Model) -> keras.Model:
    """An uncompiled clone with `model`'s weights and view: saved, it carries no optimizer state.

    Args:
        model: a tf_keras model.
    Returns:
        The clone.
    """
    clone = keras.models.clone_model(model)
    for source, layer in zip(model.layers, clone.layers):  # per layer: a model's weight order puts frozen ones last
        layer.set_weights(source.get_weights())
        layer.trainable = True  # frozen layers are a training-time choice, not part of the model
    return with_facts_of(clone, model)


def save_for_inference(model: keras.Model, path) -> None:
    """Save weights and architecture without optimizer state (.keras or .h5), as the paper's sizes count, the
    model's view (`view_of`) when it is not the whole frame at its input size, and its keypoint schema when it was
    given one (`given_schema`).

    Args:
        model: a tf_keras model.
        path: the file (its suffix chooses the format).
    """
    from pathlib import Path

    clone = inference_copy(model)
    if Path(path).suffix == ".h5":
        Path(path).write_bytes(h5_bytes(clone))
    else:
        clone.save(path)  # .keras: a zip written by Python (HDF5 only in memory inside it)
    entries = {}
    if (view := view_of(model)).crop is not None:
        entries[VIEW_ENTRY] = json.dumps(view.to_json(), sort_keys=True)
    if (schema := given_schema(model)) is not None:
        entries[SCHEMA_ENTRY] = json.dumps(schema.to_dict(), sort_keys=True)
    if entries:
        _store_entries(path, entries)


def load_model(path) -> keras.Model:
    """Load a .keras or .h5 model file for inference, with its stored view and its keypoint schema
    (`read_stored_schema`).

    Args:
        path: the model file.
    Returns:
        The model, uncompiled.
    Raises:
        UserError: a missing or unreadable file, another format, a stored view that does not fit the input, a stored
            schema that does not fit the maps, or an input size that is not fixed (`check_fixed_input`).
    """
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: model file not found")
    if path.suffix not in (".keras", ".h5"):
        raise UserError(f"{path}: expected a Keras model file (.keras or .h5)"
                        + ("; use a .tflite with `run`, `bench` or `evaluate`" if path.suffix == ".tflite" else ""))
    try:
        model = keras.models.load_model(native_name(path), compile=False, custom_objects=_application_layers())
    except Exception as exc:  # keras raises many types for a corrupt file
        raise UserError(f"{path}: cannot be read as a Keras model ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from exc
    check_fixed_input(model, path)
    view = read_stored_view(path)
    if view is not None:
        if view.shape != tuple(model.input_shape[1:3]):
            raise UserError(f"{path}: its stored view ({view.describe()}) does not fit its "
                            f"{model.input_shape[1]}x{model.input_shape[2]} input")
        with_view(model, view)
    shape = model.output_shape
    if isinstance(shape, tuple) and len(shape) == 4 and shape[-1]:  # maps (`prune` loads other CNNs too)
        if (schema := read_stored_schema(path, int(shape[-1]))) is not None:
            with_schema(model, schema)
    return model


def _application_layers() -> dict:
    """tf_keras.applications layers tf_keras does not register for loading: ConvNeXt's LayerScale and StochasticDepth
    (without them tf_keras cannot read back its own ConvNeXt files: "Unknown layer: 'LayerScale'")."""
    try:
        from tf_keras.src.applications import convnext
    except ImportError:  # a tf_keras that moved its private tree
        return {}
    return {"LayerScale": convnext.LayerScale, "StochasticDepth": convnext.StochasticDepth}


def check_fixed_input(model: keras.Model, path=None) -> None:
    """Refuse a model whose input height or width is not fixed (None), saying how to fix it.

    Every command runs FCN-Pose at one H x W size (preprocessing, target maps, the static TFLite input).

    Args:
        model: a tf_keras model.
        path: its file, to name in the error (default: the model's name).
    Raises:
        UserError: the input size is not fixed.
    """
    shape = model.input_shape
    if isinstance(shape, tuple) and len(shape) == 4 and (shape[1] is None or shape[2] is None):
        raise UserError(f"{path or model.name}: the input size is not fixed (input shape {shape}); FCN-Pose runs "
                        "at one H x W size: rebuild the model on tf_keras.Input((H, W, 3)) (multiples of 32, "
                        "e.g. 224 x 224), copy the weights over (new.set_weights(old.get_weights())) and save that")
