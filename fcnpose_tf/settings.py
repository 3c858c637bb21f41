"""Training, retraining and compression settings, each defined once: name, type, default, check, help.

The `train`, `compress` and `sweep` commands generate their options from these definitions
(`Setting.add_to`), and `train.FitConfig`, `options.CompressOptions` and `sweep.jobs.SweepConfig`
declare their fields with them (`Setting.field`), so a default, its check and its error message
live here only. Where two commands use the same setting with a different default (base training
against retraining, one training run against a sweep of many), both variants are defined below,
each with its reason.

Every setting has a value per preset (PRESETS): `recommended`, the default everywhere (what measured
best on a user's frames), and `paper`, the paper's recipe. A command's `--preset` and a config class's
`preset(name, ...)` read the same values, so `CompressOptions(rate=0.7)` is `compress --rate 0.7` and
`CompressOptions.preset("paper", rate=0.7)` is `compress --preset paper --rate 0.7`. A value of None
("auto") is resolved per run by the library (`train.FitConfig.resolved`, `options.CompressOptions.resolved`),
except `train`'s view and augmentation, which its command resolves from the frames before the checkpoint check.

Imports only the standard library: the CLI builds its parser from this module on a Pi without
TensorFlow or numpy, and `sweep.jobs` (which imports no numpy) embeds it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Any, Callable, TypeVar

from fcnpose_tf.bundled import KERAS_SUFFIXES, names_help
from fcnpose_tf.errors import UserError

Config = TypeVar("Config")
"""A configuration dataclass whose fields are settings (`config_class`): FitConfig, CompressOptions, ..."""

_SAME = object()
"""`Setting(paper=...)` not given: the paper's value is the default."""

REQUIRED = dataclasses.MISSING
"""Default of a setting every caller must give (the compression rate)."""

PRESETS = {
    "recommended": "what measured best on a user's frames (docs/training.md, docs/compression.md)",
    "paper": "the paper's recipe: random start, plain binary cross-entropy, constant learning rate, L1 ranking at "
             "the paper's widths, the paper's epoch budgets, float16 only",
}
"""The named sets of defaults; each setting's value under `paper` is its `paper` attribute."""
DEFAULT_PRESET = "recommended"


class Setting:
    """One option: its attribute name, type, default, check, help text and the message a bad value gets.

    `variant` derives a setting that differs only in what it overrides (another default, name or
    help); everything else, the check and its message among it, is read from the original, so a
    change here reaches every variant.
    """

    def __init__(self, name: str, type: Callable[[str], Any], default: Any, help: str, *, label: str,
                 check: Callable[[Any], bool] | None = None, requirement: str = "", metavar: str | None = None,
                 choices: tuple[Any, ...] | None = None, parse: Callable[[str], Any] | None = None,
                 paper: Any = _SAME) -> None:
        self.name = name
        self.paper = default if paper is _SAME else paper
        self.type = type
        self.parse = parse
        self.default = default
        self.help = help
        self.label = label
        self.check = check
        self.requirement = requirement
        self.metavar = metavar
        self.choices = choices

    def variant(self, **overrides: Any) -> Setting:
        """This setting with some attributes replaced (e.g. name, default, help); the rest stays shared.

        The paper's value is the option's, not the command's: a variant keeps it unless it overrides `paper`."""
        return _Variant(self, overrides)

    def default_in(self, preset: str) -> Any:
        """The value under the named preset (PRESETS): `default` for recommended, `paper` for the paper's recipe."""
        if preset not in PRESETS:
            raise UserError(f"preset must be one of {', '.join(PRESETS)}, got {preset!r}")
        return self.paper if preset == "paper" else self.default

    @property
    def flag(self) -> str:
        """The command-line option: --name-with-dashes."""
        return "--" + self.name.replace("_", "-")

    def validate(self, value: Any) -> Any:
        """Return `value` if it is allowed (None too when the option's default is None), else raise UserError."""
        if value is None and self.accepts_none:
            return value
        if self.choices is not None:
            if value not in self.choices:
                raise UserError(f"{self.label} must be one of {', '.join(map(str, self.choices))}, got {value!r}")
        elif self.check is not None and not (_is_type(value, self.type) and self.check(value)):
            raise UserError(f"{self.label} must be {self.requirement}, got {value!r}")
        return value

    @property
    def accepts_none(self) -> bool:
        """None is a value (no time budget, no floor) when the default is None here or in the setting this varies:
        `train`'s 30-minute budget is a variant of a budget that compression leaves unset."""
        base = self.__dict__.get("_base")
        return self.default is None or (base is not None and base.accepts_none)

    def field(self) -> Any:
        """A dataclass field holding this setting: its recommended default (read when an instance is made) and the
        setting."""
        metadata = {_SETTING: self}
        if self.default is REQUIRED:
            return dataclasses.field(metadata=metadata)
        return dataclasses.field(default_factory=lambda: self.default, metadata=metadata)

    def add_to(self, parser: argparse.ArgumentParser | argparse._ArgumentGroup, flag: str | None = None) -> None:
        """Add this setting as `flag` (default: its own --flag) with its type, choices and help.

        Left out, the option takes its value from the command's --preset (recommended without one) once the
        arguments are parsed (`fill_from_preset`): argparse sees no default, and the help states both. A bool
        setting is a flag, off unless given (its default is not shown).
        """
        flag_only = self.type is bool
        kwargs: dict[str, Any] = {"action": "store_true"} if flag_only else {"metavar": self.metavar}
        if not flag_only and self.parse is not None:
            kwargs["type"] = self.parse
        elif not flag_only and self.type is not str:
            kwargs["type"] = self.type
        if self.choices is not None:
            kwargs["choices"] = self.choices
        if self.default is REQUIRED:
            kwargs["required"] = True
        else:
            kwargs["default"] = argparse.SUPPRESS
        help_text = self.help
        shown = [] if self.default in (None, REQUIRED) or flag_only else [f"default: {_shown(self.default)}"]
        if any(action.dest == "preset" for action in parser._actions) and self.paper != self.default:
            shown.append(f"--preset paper: {_shown(self.paper)}")
        if shown and "%(default)" not in help_text:
            help_text = f"{help_text} ({'; '.join(shown)})"
        action = parser.add_argument(flag or self.flag, dest=self.name, help=help_text, **kwargs)
        action.setting = self  # read by fill_from_preset


class _Variant(Setting):
    """A setting whose attributes are read from `base` unless overridden (see Setting.variant)."""

    def __init__(self, base: Setting, overrides: dict[str, Any]) -> None:  # noqa: D107 - no Setting.__init__
        self.__dict__.update(overrides)
        self._base = base

    def __getattr__(self, name: str) -> Any:  # only called for attributes not overridden
        if name == "_base":
            raise AttributeError(name)
        return getattr(self._base, name)


_SETTING = "fcnpose_tf.setting"


def _shown(value: Any) -> str:
    """A default as a user would type it: float16,int8 for a tuple, none for None."""
    if isinstance(value, (tuple, list)):
        return ",".join(map(str, value))
    return "none" if value is None else str(value)


def add_preset_argument(parser: argparse.ArgumentParser) -> None:
    """--preset NAME, added before the command's settings (their help then names the paper's values)."""
    parser.add_argument("--preset", choices=tuple(PRESETS), default=DEFAULT_PRESET,
                        help="the defaults of every option not given: " + "; ".join(
                            f"{name}: {text}" for name, text in PRESETS.items()))


GIVEN = "given_settings"
"""The attribute of a parsed namespace naming the settings given on the command line (the rest came from a preset)."""


def fill_from_preset(parser: argparse.ArgumentParser, namespace: argparse.Namespace) -> argparse.Namespace:
    """Give every setting of `parser` that the command line left out its value under the namespace's --preset
    (recommended without one); record the names that were given in `namespace.given_settings`."""
    preset = getattr(namespace, "preset", DEFAULT_PRESET)
    given = set(getattr(namespace, GIVEN, ()))
    for action in parser._actions:
        setting = getattr(action, "setting", None)
        if setting is None:
            continue
        if hasattr(namespace, action.dest):
            given.add(action.dest)
        else:
            setattr(namespace, action.dest, setting.default_in(preset))
    setattr(namespace, GIVEN, frozenset(given))
    return namespace


def _is_type(value: Any, kind: Callable) -> bool:
    if isinstance(value, bool):
        return False
    if kind is int:
        return isinstance(value, int)
    if kind is float:
        return isinstance(value, (int, float)) and math.isfinite(value)
    return True


def config_class(*entries: Setting | tuple[str, Setting]) -> Callable[[type], type]:
    """Class decorator: make `cls` a dataclass whose fields are these settings, in this order.

    Each field takes its name (unless given as a (name, setting) pair), type and default from its
    setting, so a configuration class states only which settings it holds; `validate` (added
    unless the class defines one) checks each with its setting's message, and `preset(name, **values)`
    makes an instance with the named preset's values for every field not given (`from_preset`).
    """
    def decorate(cls: type) -> type:
        annotations: dict[str, str] = {}
        for entry in entries:
            name, setting = entry if isinstance(entry, tuple) else (entry.name, entry)
            kind = getattr(setting.type, "__name__", "Any")
            annotations[name] = f"{kind} | None" if setting.default is None else kind
            setattr(cls, name, setting.field())
        cls.__annotations__ = {**annotations, **cls.__dict__.get("__annotations__", {})}
        if "validate" not in cls.__dict__:
            cls.validate = validate_fields
        cls.preset = classmethod(from_preset)
        return dataclasses.dataclass(cls)
    return decorate


def from_preset(config_type: type[Config], preset: str, **values: Any) -> Config:
    """A configuration with the named preset's values.

    Args:
        config_type: a dataclass whose fields are declared with `Setting.field`.
        preset: a name of PRESETS.
        **values: fields given (a required one, such as the rate, must be).
    Returns:
        The configuration: each field of `values` as given, every other setting at its value under `preset`.
    Raises:
        UserError: an unknown preset.
    """
    return config_type(**{**_preset_values(config_type, preset), **values})


def _preset_values(config_type: type, preset: str) -> dict[str, Any]:
    """The value under `preset` of every field of dataclass `config_type` declared with `Setting.field`
    (a required one, such as the rate, is left out)."""
    values = {}
    for f in dataclasses.fields(config_type):
        setting = f.metadata.get(_SETTING)
        if setting is not None and setting.default is not REQUIRED:
            values[f.name] = setting.default_in(preset)
    return values


def carried(source: Any, config_type: type[Config], *, renamed: dict[str, str] | None = None,
            **given: Any) -> Config:
    """A configuration read from another one (the sweep's settings to a run's FitConfig and CompressOptions).

    Args:
        source: what the values are read from, by attribute.
        config_type: the dataclass to make.
        renamed: field of `config_type` -> attribute of `source`, where the names differ.
        **given: fields given, taking precedence over `source`.
    Returns:
        The configuration, every field read from `source` unless given.
    Raises:
        TypeError: `source` lacks a field's attribute (a value a config holds is never dropped on the way to
            another).
    """
    renamed = renamed or {}
    values = {}
    for f in dataclasses.fields(config_type):
        if f.name in given:
            values[f.name] = given[f.name]
            continue
        attribute = renamed.get(f.name, f.name)
        if not hasattr(source, attribute):
            raise TypeError(f"{type(source).__name__} has no {attribute!r} for {config_type.__name__}.{f.name}")
        values[f.name] = getattr(source, attribute)
    return config_type(**values)


def validate_fields(config: Any) -> None:
    """Check every field of the dataclass instance `config` declared with `Setting.field`; UserError if bad."""
    for f in dataclasses.fields(config):
        setting = f.metadata.get(_SETTING)
        if setting is not None:
            setting.validate(getattr(config, f.name))


def from_args(args: argparse.Namespace, config_type: type[Config], *, renamed: dict[str, str] | None = None,
              **given: Any) -> Config:
    """A configuration from a command's parsed options.

    Args:
        args: the parsed options.
        config_type: the dataclass to make.
        renamed: field of `config_type` -> option's attribute in `args`, where the names differ.
        **given: fields given, taking precedence over `args`.
    Returns:
        The configuration: each field from the option of its name where `args` holds one, else `given`'s value or
        the field's default.
    """
    renamed = renamed or {}
    names = {f.name: renamed.get(f.name, f.name) for f in dataclasses.fields(config_type)}
    values = {field: getattr(args, attr) for field, attr in names.items() if hasattr(args, attr)}
    return config_type(**{**values, **given})


def thread_count(text: str) -> int:
    """argparse type of every command's --threads: a whole number of CPU threads, at least 1.

    Checked while parsing, before TensorFlow or LiteRT sees it: TensorFlow aborts the process on a
    count below 1, and 0 would be reported as "0 thread(s)".
    """
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of threads (at least 1), got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1 thread, got {value}")
    return value


def thread_counts(text: str) -> tuple[int, ...]:
    """argparse type of a list of thread counts (`bench --threads 1,2,4`): each a `thread_count`, de-duplicated."""
    counts: list[int] = []
    for part in str(text).split(","):
        try:
            value = thread_count(part.strip())
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected positive integers separated by commas, e.g. 1,2,4") from None
        if value not in counts:
            counts.append(value)
    return tuple(counts)


def check_input_size(input_size: int) -> int:
    """Return input_size if FCN-Pose can take it (a positive multiple of 32), else raise UserError."""
    return INPUT_SIZE.validate(input_size)


INPUT_SIZE_MULTIPLE = 32
"""FCN-Pose pools 5 times by 2 (model.NUM_POOLS), so its input side is a multiple of 2**5."""

# ------------------------------------------------------------------------------------------
# Model and data
# ------------------------------------------------------------------------------------------

MAX_INPUT_SIDE = 1024
"""An input side at most: 1024 x 1024 costs 21x the paper's 224 x 224 (31 G multiply-adds a frame) and a training
batch of 8 needs about 3 GB; a larger side is a typing slip, refused before anything is allocated."""

INPUT_SIZE = Setting(
    "input_size", int, 224, f"model input side, a multiple of {INPUT_SIZE_MULTIPLE}; 320 or 384 localise finer where "
    "the arm is small in the frame, at 2-3x the compute (docs/training.md, \"Someone else's arm\")", label="input size",
    check=lambda v: 0 < v <= MAX_INPUT_SIDE and v % INPUT_SIZE_MULTIPLE == 0,
    requirement=f"a positive multiple of {INPUT_SIZE_MULTIPLE} (FCN-Pose pools 5 times by 2), at most {MAX_INPUT_SIDE}")
AUTO_INPUT_SIZE = "auto"


def input_size_or_auto(text: str) -> int | str | tuple[int, int]:
    """argparse type of train's --input-size: auto (chosen from where the arm is and how large), a whole number S
    (S x S) or HxW (e.g. 224x288; each checked against FCN-Pose's multiple of 32 by the setting)."""
    if text.strip().lower() == AUTO_INPUT_SIZE:
        return AUTO_INPUT_SIZE
    try:
        parts = [int(part) for part in text.lower().replace(" ", "").split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        return parts[0]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise argparse.ArgumentTypeError(
        f"expected auto, S or HxW (multiples of {INPUT_SIZE_MULTIPLE}, e.g. 224 or 224x288), got {text!r}")


def _input_shape_ok(value: Any) -> bool:
    if _is_type(value, int):
        return INPUT_SIZE.check(value)
    return (isinstance(value, tuple) and len(value) == 2 and all(_is_type(v, int) and INPUT_SIZE.check(v)
                                                                   for v in value))


TRAIN_INPUT_SIZE = INPUT_SIZE.variant(
    default=AUTO_INPUT_SIZE, type=str, parse=input_size_or_auto, metavar="auto|S|HxW",
    check=lambda v: v == AUTO_INPUT_SIZE or _input_shape_ok(v),
    requirement=f"auto, S or HxW (positive multiples of {INPUT_SIZE_MULTIPLE}: FCN-Pose pools 5 times by 2; at most "
                f"{MAX_INPUT_SIDE})",
    help="the model's input: auto takes a fixed camera's workspace crop at its own aspect and the fewest pixels, "
         "up to 224x288's, at which the arm's keypoint box spans 140 input pixels in the median frame (where views "
         "vary: the whole frame at the smallest square side from 224 to 384 that does; docs/training.md, \"Input "
         "size\"), or the starting model's own view where the arm spans "
         "140 pixels there too and its crop holds every keypoint of frames of its aspect, and keeps the starting model as saved if it scores "
         "higher on the validation frames; or S (S x S) or HxW, multiples of 32")
"""`train` serves a user's camera: where the arm is small in the input, PCK@0.05's radius is a few input pixels
wide and fine localisation falls (measured on the held-out fixed camera: docs/training.md, "Someone else's
arm"); `data.arm_size` measures where the arm is and how large, and chooses. The paper's preset keeps the paper's
224 x 224 over the whole frame."""
ARCHITECTURE = Setting(
    "architecture", str, "fcn-pose",
    "fcn-pose: the paper's network; fcn-pose-skip: the same with conv2's half-resolution block added before conv10 "
    "(a zero-initialised 1x1 convolution: it starts as the model it is fine-tuned from), so the maps are read from "
    "2 x 2 instead of 4 x 4 blocks, +3.5 %% MACs; finer keypoints where the arm is small (docs/training.md, "
    "\"Architecture\"). compress and `fcnpose-tf prune` prune either (conv9 and the skip as one group); the sweep "
    "prunes the paper's fcn-pose",
    label="architecture", choices=("fcn-pose", "fcn-pose-skip"), paper="fcn-pose")
"""`train`'s network; a model given to --init keeps its own unless this adds the skip (`model.as_architecture`)."""
FINE_TUNE_ARCHITECTURE = "fcn-pose-skip"
"""The network `train` makes of the bundled generalist (plain FCN-Pose; the skip added at zero) when --architecture
is not given: finer keypoints on the held-out fixed camera (two seeds), the new cell, random views and held-out
random views, measured against FCN-Pose (docs/training.md, "Architecture")."""
TRAIN_CROP = Setting(
    "crop", str, "auto", "what of the frame the network sees: auto: with --input-size auto, a fixed camera's workspace "
    "(the box holding every training keypoint, 5 %% more on each side, at the input's aspect) and the whole frame "
    "where views vary; with a given --input-size, the whole frame (as before crops existed); workspace: the "
    "workspace crop at any input size; none: the whole frame (the paper's). The crop is part of the model: stored "
    "in it and in every export, applied by every command and the Pi runtime", label="crop",
    choices=("auto", "workspace", "none"), paper="none")
"""A fixed camera's arm never leaves its workspace, so pixels outside it are spent on nothing
(docs/training.md, "Input size")."""
FOLDS = Setting("folds", int, 5, "K of the K-fold cross-validation splits (the paper: 5)", label="folds",
                check=lambda v: v >= 2, requirement="at least 2", metavar="K")
TRAIN_FOLDS = FOLDS.variant(
    default=None, paper=None, help="train one model per fold of K-fold cross-validation (the paper: 5)")
"""`train` trains on the 80/20 hold-out split unless --folds asks for one model per fold."""
FOLD = Setting("fold", int, None, "train only fold k (0-based) of the K folds", label="fold",
               check=lambda v: v >= 0, requirement="a fold index (0-based)", metavar="k")
RETRAIN_FOLD = FOLD.variant(help="retrain on fold k instead of the base model's split")
"""`compress` retrains on the base model's own split unless told otherwise."""
AUGMENT = Setting(
    "augment", str, "paper",
    "paper: the paper's fixed offline rotation/padding copies (--augment-copies); online: fresh keypoint-aware "
    "random transforms for every sample of every epoch (flip, rotation, zoom, shift, colour, blur, noise, JPEG, "
    "occluding patches; docs/data.md)", label="augmentation", choices=("paper", "online"))
"""The paper's copies: they measured better than online augmentation within train's 30-minute budget on a fixed
camera, and they reproduce the paper's tables in `compress` and `sweep`; online augmentation is the option for views
that vary (the figures: docs/results.md, "Training history")."""
TRAIN_AUGMENT = AUGMENT.variant(
    default="auto", choices=("auto", "paper", "online"),
    help="auto: paper for frames of one fixed camera, online when the views vary (measured on the frames: "
         "docs/training.md); paper: the paper's fixed offline rotation/padding copies (--augment-copies); "
         "online: fresh keypoint-aware random transforms for every sample of every epoch (flip, rotation, zoom, "
         "shift, colour, blur, noise, JPEG, occluding patches; docs/data.md)")
"""`train` serves a user's frames, whichever camera set-up they come from: on the new fixed cell the paper's
copies measured ahead, on random views online augmentation (docs/training.md, "Training on your own frames");
`data.views` tells the two apart from the frames themselves."""
INHERITED_AUGMENT = AUGMENT.variant(
    default=None, paper="paper",
    help="paper: the paper's fixed offline rotation/padding copies (--augment-copies); online: fresh keypoint-aware "
         "random transforms for every sample of every epoch (docs/data.md); default: the base model's, from its "
         "NAME_train.json (online for a model `train` fitted to views that vary), else paper")
"""`compress` retrains with the augmentation the base model was trained with, as with its keypoint weight: a model
fine-tuned on views that vary, retrained on the paper's fixed copies of its 192 frames, overfits within a few
epochs and loses PCK@0.5 (docs/compression.md, "What to expect")."""
AUGMENT_COPIES = Setting("augment_copies", int, 2, "with --augment paper: offline rotation/padding copies per training frame (the paper: 2)",
                         label="augmented copies", check=lambda v: v >= 0, requirement=">= 0", metavar="N")
INHERITED_AUGMENT_COPIES = AUGMENT_COPIES.variant(
    default=None, paper=2,
    help="with --augment paper: offline rotation/padding copies per training frame (default: the base model's, from "
         "its NAME_train.json, else 2, the paper's)")
"""`compress` retrains on as many copies as the base model was trained on, as it inherits its augmentation and keypoint
weight: a pruned network retrained on fewer copies than its base lost more of its fine localisation
(docs/compression.md, "Compress a model", the defaults table)."""
TRAIN_AUGMENT_COPIES = AUGMENT_COPIES.variant(
    default=None, paper=2,
    help="with --augment paper: offline rotation/padding copies per training frame (default: 4 when fine-tuning an "
         "fcn-pose-skip network on one fixed camera, else 2, the paper's)")
"""`train`'s copies; `train_augment_copies` resolves the default per run."""
INIT = Setting(
    "init", str, "generalist", "start from this model's weights (trained at any input size for the same keypoints): "
    f"a .keras/.h5 file, a bundled model by name ({names_help(KERAS_SUFFIXES)}; refused for data of another keypoint "
    "schema), or none: random weights, as the paper. A trained start is the model to beat: if no epoch improves on "
    "its validation loss, it is written unchanged", label="initial weights", metavar="MODEL|NAME|none", paper="none")
"""`train` fine-tunes the bundled generalist: measured on two proxies of a user's frames (docs/training.md,
"Training on your own frames")."""
SEED = Setting("seed", int, 0, "seed of weights, augmentation and batch order", label="seed",
               check=lambda v: 0 <= v < 2 ** 32, requirement="a whole number from 0 to 2**32 - 1")
"""The range numpy's seeding takes (a negative seed ended a run in a traceback)."""
SPLIT_SEED = SEED.variant(name="split_seed", label="split seed", default=None, paper=None,
                          help="seed of the dataset's splits (which frames are validation frames)")
"""Checked where splits are made or looked up (`data.splits.load_or_create_splits`): given as --split-seed, or
taken from a model's training record."""

# ------------------------------------------------------------------------------------------
# Optimisation (base training and retraining)
# ------------------------------------------------------------------------------------------

EPOCHS = Setting("epochs", int, 500, "maximum epochs, with early stopping (the paper: 500)", label="epochs",
                 check=lambda v: v >= 1, requirement="at least 1")
SWEEP_EPOCHS = EPOCHS.variant(
    default=60, help="base-model epochs, with early stopping (the paper: up to 500, converging near 60)")
"""A sweep trains one base model per fold before it prunes anything; its base models converge near
60 epochs, so 500 would only spend hours on early stopping's patience."""
KEEP_BEST = Setting(
    "keep_best", str, "keypoints",
    "which epoch is kept and what early stopping and the plateau's halving wait on: keypoints, the validation frames' "
    "keypoints read as the model's files are (the mean of PCK@0.5, @0.2 and @0.05, then the EPE); loss, the lowest "
    "validation loss (the paper's)", label="kept epoch", choices=("keypoints", "loss"), paper="loss")
"""`compress`'s retraining keeps the epoch whose validation keypoints score best: on the bundled task the lowest
validation loss came while fine localisation was still improving, and on the hardest proxy the two rules' picks were
within epoch-to-epoch noise (docs/compression.md, "Retraining in fcnpose-tf compress", the kept epoch)."""
TRAIN_KEEP_BEST = KEEP_BEST.variant(default="loss")
"""`train` keeps the lowest validation loss: on the hardest proxy the keypoints' rule measured the same
(docs/results.md, "The kept epoch by the validation keypoints"), and its fixed-camera proxies are not measured yet."""
PATIENCE = Setting("patience", int, 20, "stop after this many epochs without a better validation score (--keep-best)",
                   label="patience", check=lambda v: v >= 1, requirement="at least 1", metavar="N")
TRAIN_PATIENCE = PATIENCE.variant(default=12)
"""With the learning rate halved every 4 epochs without progress (TRAIN_LR_PATIENCE), 12 epochs of patience
allow three halvings before stopping: the bundled baseline's recipe (saved_models/PROVENANCE.md)."""
RETRAIN_PATIENCE = PATIENCE.variant(
    name="retrain_patience", default=5, paper=5, label="retraining patience",
    help="early-stopping patience while retraining")
"""The sweep's retraining patience: the paper states none, and its tables were reproduced with 5."""
COMPRESS_RETRAIN_PATIENCE = RETRAIN_PATIENCE.variant(default=10)
"""`compress`'s: the validation loss of a retraining over a few hundred frames is noisy, its plateaus last up to 7
epochs before a better one (halving the learning rate after 3), and the epochs past them placed keypoints more finely;
within the 25 epochs and the time budget, early stopping after 10 mostly only ends an idle run that has converged
(docs/compression.md, "Retraining"). `--preset paper` keeps 5."""
RETRAIN_EPOCHS = Setting(
    "retrain_epochs", int, 25, "retraining epochs with early stopping (the paper: up to 100); 0 skips retraining",
    label="retrain epochs", check=lambda v: v >= 0, requirement=">= 0", paper=100)
"""Default retraining budget: keeps `compress --rate 0.7` within ~10 minutes on 2 cores (measured:
11 min 55 s wall with a sweep job sharing one of the two cores; held-out PCK@0.5 0.946 against the
base's 0.966, the same as 40 epochs). The paper retrains up to 100 epochs until convergence: its preset."""
RETRAIN_EPOCHS_BY_RATE = RETRAIN_EPOCHS.variant(
    type=str, check=None, metavar="E[,RATES=E]",
    help="retraining epochs after pruning, with early stopping (the paper: up to 100); RATES=E items give some "
         "rates their own budget, e.g. 10,0.6:0.9:0.1=40 (heavier pruning needs longer to converge)")
"""The sweep's form: one budget, or one per rate (read by `sweep.rates.parse_per_rate_epochs`)."""
def minutes_or_none(text: str) -> float | None:
    """argparse type of the time budgets: a number of minutes, or `none` (no budget)."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected minutes or none, got {text!r}") from None


MAX_MINUTES = Setting(
    "max_minutes", float, None, "time budget: no new epoch starts after this many minutes of training (default: "
    "none; the epochs and early stopping decide)", label="time budget", check=lambda v: v > 0 and math.isfinite(v),
    requirement="a positive number of minutes, or none", metavar="MIN", parse=minutes_or_none)
TRAIN_MAX_MINUTES = MAX_MINUTES.variant(
    help="time budget: no new epoch starts after this many minutes of training (the paper's 500 epochs would "
         "take days here; none: the epochs and early stopping decide)", default=30.0)
"""`train` sets its budget by time, not by the paper's 500 epochs: 30 minutes on 2 CPU cores fine-tunes a
bundled model on a few hundred frames (docs/training.md, "Training on your own frames"). Compression and
the sweep keep epoch budgets (their tables compare rates at equal epochs)."""
MIN_RETRAIN_MINUTES = 2.0
"""The least a total budget leaves the retraining (`retraining_minutes`): a run whose first steps took most of the
budget still retrains a few epochs, and says that it goes over."""
COMPRESS_MAX_MINUTES = MAX_MINUTES.variant(
    default=10.0, paper=None,
    help="retraining time budget: no new retraining epoch starts after this many minutes (less when --total-minutes "
         "leaves less; none: the epochs and early stopping decide, the same epochs on any machine)")
"""A user's model fine-tuned at 384 retrained 25 epochs for 42 minutes on 2 shared cores; 10 minutes of retraining
and the steps around it end `compress` in about 15 (docs/compression.md, "Time budget"). The bundled baseline's
retraining ends before it on an idle 2-core machine; the paper's preset has none (its 100 epochs decide)."""
COMPRESS_TOTAL_MINUTES = MAX_MINUTES.variant(
    name="total_minutes", default=15.0, paper=None, label="total time budget",
    help="the whole run's time budget: the retraining gets what is left of it once the steps before it are done, "
         "keeping for the steps after (exporting, verifying, measuring) twice what the steps before took apart from "
         "ranking filters, at least "
         f"{MIN_RETRAIN_MINUTES:g} and at most --max-minutes (none: --max-minutes alone)")
"""`compress --rate 0.7` ends in about 15 minutes on 2 cores whatever the input: the steps around the retraining took
2.5 minutes on a 224 x 256 model and 8.2 on a 288 x 288 one beside another run, which made the second 19 minutes
with a fixed 10-minute retraining (docs/compression.md, "Time budget"). The paper's preset and the sweep have none
(their epochs decide)."""
SWEEP_MAX_MINUTES = MAX_MINUTES.variant(
    help="time budget of each base model's training: no new epoch starts after this many minutes (default: none; "
         "the epochs and early stopping decide)")
BATCH_SIZE = Setting("batch_size", int, 8, "training batch size", label="batch size",
                     check=lambda v: v >= 1, requirement="at least 1")
LEARNING_RATE = Setting("learning_rate", float, 1e-3, "Adam learning rate", label="learning rate",
                        check=lambda v: v > 0, requirement="a positive number")
COMPRESS_LEARNING_RATE = LEARNING_RATE.variant(
    default=3e-3, help="Adam learning rate of the retraining (the paper's: 1e-3)")
"""A pruned network retrained at the paper's 1e-3 is still improving after 25 epochs (and after 65 with the rate
halved on plateaus); 3e-3, halved after 3 stale epochs, converges further within the same 25
(docs/compression.md, "Retraining budget"). The library and the sweep keep 1e-3."""
TRAIN_LEARNING_RATE = LEARNING_RATE.variant(
    default=None, help="Adam learning rate (default: 3e-3 when fine-tuning an fcn-pose-skip network on the paper's "
                       "copies, i.e. one fixed camera; 1e-3 otherwise, the paper's)")
"""`train`'s rate; `train_recipe` resolves the default per run."""
SKIP_FINE_TUNE_LEARNING_RATE = 3e-3
"""With the skip, fine-tuning on one fixed camera trains conv2 onwards at compress's retraining rate (`train_recipe`)."""
SKIP_FINE_TUNE_FREEZE = 1
"""With the skip, fine-tuning on one fixed camera keeps conv1 fixed and trains conv2, which the skip reads
(`train_recipe`)."""
LR_PATIENCE = Setting(
    "lr_patience", int, 0,
    "halve the learning rate after N epochs without a better validation score (again after N more; floor 1e-5); "
    "0 keeps it constant, as the paper does",
    label="learning-rate patience", check=lambda v: v >= 0, requirement="0 (off) or more epochs", metavar="N")
LR_SCHEDULE = Setting(
    "lr_schedule", str, "plateau",
    "plateau: the rate stays at --learning-rate, halved after --lr-patience epochs without a better validation "
    "score (0: never, the paper's); cosine: from --learning-rate down to 1e-5 along a half cosine over the budget, "
    "epochs or --max-minutes, whichever ends first (needs --lr-patience 0)", label="learning-rate schedule",
    choices=("plateau", "cosine"))
"""An epoch budget with a rate that ends small: retraining a pruned model at a constant rate was still
improving (and its validation loss jumping) at its last epoch (docs/compression.md, "Retraining budget")."""

DEFAULT_COMPRESS_LR_PATIENCE = 3
"""What `compress --lr-patience` resolves to on the plateau schedule: with COMPRESS_LEARNING_RATE it measured
ahead of every other schedule at 70 % within the 25-epoch budget (docs/compression.md, "Retraining budget")."""
COMPRESS_LR_PATIENCE = LR_PATIENCE.variant(
    default=None, help="halve the retraining's learning rate after N epochs without a better validation score (again "
                       f"after N more; floor 1e-5); default {DEFAULT_COMPRESS_LR_PATIENCE} (0 with --lr-schedule "
                       "cosine); 0 keeps it constant, as the paper does")


def resolved_lr_patience(lr_patience: int | None, lr_schedule: str, plateau_default: int) -> int:
    """An --lr-patience left unset: 0 on the cosine schedule (it sets every epoch's rate itself), else the
    command's default for the plateau schedule."""
    if lr_patience is not None:
        return lr_patience
    return 0 if lr_schedule == "cosine" else plateau_default


def check_lr_schedule(lr_schedule: str, lr_patience: int) -> None:
    """UserError if a cosine schedule is also asked to halve the rate on plateaus (both would set it)."""
    if lr_schedule == "cosine" and lr_patience:
        raise UserError("--lr-schedule cosine sets every epoch's learning rate itself; "
                        f"--lr-patience {lr_patience} would halve it too (use --lr-patience 0)")


DEFAULT_TRAIN_LR_PATIENCE = 4
"""What `train --lr-patience` resolves to on the plateau schedule: a few hundred frames overfit quickly at a
constant rate; halving after 4 stale epochs is the bundled baseline's recipe."""
TRAIN_LR_PATIENCE = LR_PATIENCE.variant(
    default=None, help="halve the learning rate after N epochs without a better validation score (again after N "
                       f"more; floor 1e-5); default {DEFAULT_TRAIN_LR_PATIENCE} (0 with --lr-schedule cosine); 0 keeps "
                       "it constant, as the paper does")
POSITIVE_WEIGHT = Setting(
    "positive_weight", float, 1.0,
    "weight of keypoint-disc pixels in the binary cross-entropy (1 = the paper's plain BCE; 20 converges several "
    "times faster on small discs, see docs/training.md)",
    label="positive weight", check=lambda v: v >= 1, requirement="a number >= 1")
TRAIN_POSITIVE_WEIGHT = POSITIVE_WEIGHT.variant(
    default=None, help="weight of keypoint-disc pixels in the binary cross-entropy (default: 8 when fine-tuning a "
                       "trained model on the paper's copies, i.e. one fixed camera; 20 with online augmentation or "
                       "--init none; 1 = the paper's plain BCE, with which the keypoint maps stay empty for many "
                       "epochs; docs/training.md)")
"""`train` serves a user's frames; `train_positive_weight` resolves the default per run."""
DEFAULT_FROM_SCRATCH_POSITIVE_WEIGHT = 20.0
"""Random weights under the paper's plain BCE sit on an empty-map plateau; 20 gets them off it several times faster,
and on views that vary it keeps unsure keypoints above the threshold (docs/training.md, "Loss")."""
DEFAULT_FINE_TUNE_POSITIVE_WEIGHT = 8.0
"""A trained start on one fixed camera has no empty-map plateau, and a smaller weight draws tighter discs (measured
on the new-cell proxy: docs/training.md, "Training on your own frames")."""


def train_positive_weight(trained_start: bool, augment: str) -> float:
    """`train`'s default keypoint weight: DEFAULT_FINE_TUNE_POSITIVE_WEIGHT when a trained model is fine-tuned with
    the paper's copies (what --augment auto picks for one fixed camera), else DEFAULT_FROM_SCRATCH_POSITIVE_WEIGHT
    (random weights, or online augmentation for views that vary)."""
    return DEFAULT_FINE_TUNE_POSITIVE_WEIGHT if trained_start and augment == "paper" \
        else DEFAULT_FROM_SCRATCH_POSITIVE_WEIGHT


INHERITED_POSITIVE_WEIGHT = POSITIVE_WEIGHT.variant(
    default=None, help="keypoint-pixel weight of the retraining loss (default: the base model's, from its "
                       "NAME_train.json; else 1, the paper's plain BCE)")
"""`compress` retrains with the loss the base model was trained with unless told otherwise."""
FREEZE = Setting(
    "freeze", int, 0,
    "keep the first N convolutions (conv1..convN) fixed while training: fewer gradients, faster epochs; 0 trains "
    "every layer, as the paper does", label="frozen layers", check=lambda v: 0 <= v <= 9,
    requirement="0 to 9 (conv10 always trains)", metavar="N")
TRAIN_FREEZE = FREEZE.variant(
    default=None, help="keep the first N convolutions (conv1..convN) fixed while fine-tuning: fewer gradients, "
                       "faster epochs (default: 2 when starting from a trained model, except 1 for an fcn-pose-skip "
                       "network on one fixed camera; 0 with --init none)")
"""`train` fine-tunes a pretrained start: its first layers (colour and edge filters) already fit any frame,
and their gradients are most of a training step's cost at 224 (conv1 and conv2 frozen: 2.4x faster steps).
On the new-cell proxy it reached the same accuracy as training every layer (PCK@0.05 0.800 against 0.806)
in 16 instead of 24 minutes (docs/training.md, "Training on your own frames")."""
SWEEP_FREEZE = FREEZE.variant(
    help="keep the first N convolutions (conv1..convN) of a pruned model fixed while it is retrained; the base models "
         "train every layer (they start from random weights); 0 retrains every layer, as the paper does")
DEFAULT_FINE_TUNE_FREEZE = 2
"""conv1..conv2 stay fixed when `train` starts from a trained model and --freeze is not given (but see
`train_recipe`)."""


def skip_fine_tune(trained_start: bool, augment: str, architecture: str | None) -> bool:
    """True for a run that fine-tunes an fcn-pose-skip network on the paper's copies (one fixed camera): the run
    `train_recipe` and `train_augment_copies` give their own defaults."""
    return trained_start and augment == "paper" and architecture == "fcn-pose-skip"


def train_recipe(trained_start: bool, augment: str, architecture: str | None) -> tuple[int, float]:
    """`train`'s default (freeze, learning rate) for a run. Fine-tuning an fcn-pose-skip network on the paper's copies
    (one fixed camera) keeps conv1 fixed (SKIP_FINE_TUNE_FREEZE) and trains the rest at SKIP_FINE_TUNE_LEARNING_RATE:
    the skip reads conv2, which then adapts to the user's camera, and conv1's gradients (and conv2's input gradient,
    the step's largest) are not paid for (docs/training.md, "Architecture"). Other trained starts keep conv1-2 fixed
    (DEFAULT_FINE_TUNE_FREEZE) at the paper's 1e-3; random weights train every layer at 1e-3."""
    if skip_fine_tune(trained_start, augment, architecture):
        return SKIP_FINE_TUNE_FREEZE, SKIP_FINE_TUNE_LEARNING_RATE
    return (DEFAULT_FINE_TUNE_FREEZE if trained_start else 0), float(LEARNING_RATE.default)


SKIP_FINE_TUNE_AUGMENT_COPIES = 4
"""Fine-tuning an fcn-pose-skip network on one fixed camera makes 4 copies of each frame, not the paper's 2: its
validation loss stops improving after about 15 epochs of 2 copies, and more copies are more views of the same frames
(docs/training.md, "Training on your own frames")."""


def train_augment_copies(trained_start: bool, augment: str, architecture: str | None) -> int:
    """`train`'s default --augment-copies for a run: SKIP_FINE_TUNE_AUGMENT_COPIES where `skip_fine_tune`, else
    the paper's AUGMENT_COPIES."""
    return SKIP_FINE_TUNE_AUGMENT_COPIES if skip_fine_tune(trained_start, augment, architecture) \
        else int(AUGMENT_COPIES.default)
THREADS = Setting("threads", int, None, "CPU threads for TensorFlow and LiteRT (default: all cores)",
                  label="threads", check=lambda v: v >= 1, requirement="at least 1", parse=thread_count)
SWEEP_THREADS = THREADS.variant(
    help="CPU threads per job for TensorFlow and LiteRT (default: all cores when sequential, cores / workers "
         "with --workers, 1 per Ray task); timing figures depend on it")
"""Jobs running side by side share the cores, so the sweep's default depends on the executor."""
INFERENCE_THREADS = THREADS.variant(help="inference threads (default: all cores)")
"""`evaluate` and `predict` only run a model (Keras or LiteRT) on frames."""
RUN_THREADS = THREADS.variant(help="interpreter threads (default: all cores)")
"""`run` holds a LiteRT interpreter, nothing else."""
BENCH_THREADS = THREADS.variant(
    type=tuple, parse=thread_counts, metavar="N,N,...",
    help="thread counts to compare (default: 1, 2, 4 ... up to all cores)",
    check=lambda v: len(v) > 0 and all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in v),
    requirement="one or more thread counts, each at least 1")
"""`bench` times a model at several thread counts (None: `runtime.bench.default_thread_counts`)."""

# ------------------------------------------------------------------------------------------
# Options of the commands that read frames and write files
# ------------------------------------------------------------------------------------------

MAX_FRAMES = Setting("max_frames", int, None, "stop after N frames", label="--max-frames", check=lambda v: v >= 1,
                     requirement="at least 1", metavar="N")
"""`run` and `predict` read a source until it ends (a camera: until stopped) unless given a number of frames."""
SELECT_BY = Setting(
    "by", str, "uniform", "--select's choice: uniform (evenly spread, the baseline), uncertain (low map confidence or "
    "missing keypoints), jump (keypoints off their track between consecutive processed frames), disagree (keypoints "
    "that move when the frame is flipped or zoomed out)", label="--by",
    choices=("uniform", "uncertain", "jump", "disagree"))
"""`predict --select`'s score (`correction.selection.STRATEGIES`, which a test holds equal). Uniform is the default:
DeepLabCut found uncertainty sampling no better than uniform (docs/data.md)."""
QUIET = Setting("quiet", bool, False, "no progress bars and no loop progress, also on a terminal: messages and one "
                "line per epoch (for logs; without a terminal there are no bars either)", label="--quiet")
"""Every command's progress setting (`add_command_options`): it makes the command's `progress.Reporter` quiet."""


def add_command_options(parser: argparse.ArgumentParser) -> None:
    """--debug and --quiet, which every command and subcommand (`data inspect`, `data merge`) takes."""
    parser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show full tracebacks for errors")
    QUIET.add_to(parser)


FORCE = Setting("force", bool, False, "replace existing output files", label="--force")
"""No command replaces a file that exists without it (docs/design.md, conventions); a command names what it replaces
in its own words (`FORCE.variant(help=...)` where it adds the option)."""

# ------------------------------------------------------------------------------------------
# Decoding (maps to keypoints), shared by evaluate, run, predict and bench
# ------------------------------------------------------------------------------------------

THRESHOLD = Setting("threshold", float, 0.5, "map probability above which a pixel belongs to a keypoint "
                    "(Algorithm 1; the paper: 0.5)", label="threshold", check=lambda v: 0 < v < 1,
                    requirement="between 0 and 1 (exclusive)", metavar="P")
FALLBACK = Setting(
    "fallback", float, None, "read a keypoint whose map has no pixel above --threshold from its pixels above P "
    "instead of reporting it missing (e.g. 0.2: finds keypoints a model is unsure of on unfamiliar views; "
    "default: missing, as the paper; docs/postprocess.md)", label="fallback threshold", metavar="P")
"""Checked against --threshold by `postprocess.check_fallback`, where every decoder takes it."""


CENTROID = Setting(
    "centroid", str, "weighted", "where in its cluster a keypoint is read: weighted, each pixel weighted by "
    "(p - threshold)^2 (PCK@0.05 +0.01-0.04 on held-out looks and pruned int8 files), or plain, the mean of the "
    "cluster's pixels (Algorithm 1, the paper's); docs/postprocess.md", label="centroid", choices=("weighted", "plain"))
"""Every decoder's default (`postprocess.CENTROIDS`; the library's signatures repeat it, and a test holds them
to it)."""
CLUSTER = Setting(
    "cluster", str, "largest", "which of a map's clusters is the keypoint: largest (Algorithm 1, the paper's) or "
    "chain, one per map chosen jointly along the arm by the clusters' sizes, the skeleton map between consecutive "
    "keypoints and the UR5's limb lengths (PCK@0.5 +0.01-0.03 on looks the model was not trained on, about the "
    "same elsewhere; about 1 ms more a frame); docs/postprocess.md", label="cluster choice",
    choices=("largest", "chain"))
"""Every decoder's default (`postprocess.CLUSTERS`)."""
SWEEP_CENTROID = CENTROID.variant(
    default="plain", paper="plain", help="where in its cluster a keypoint is read: plain (the default: Algorithm 1, the paper's, so "
    "the sweep reproduces its tables and a results folder resumes runs made before) or weighted (the other commands' "
    "default; docs/postprocess.md)")
"""The sweep measures the paper's protocol; a results folder holds jobs of one decoding (`sweep.jobs.KEY_FIELDS`)."""


def add_decoding_arguments(parser: argparse.ArgumentParser, fallback: bool = True) -> None:
    """--threshold, --centroid, --cluster (and --fallback) for a command that decodes maps into keypoints."""
    THRESHOLD.add_to(parser)
    CENTROID.add_to(parser)
    CLUSTER.add_to(parser)
    if fallback:
        FALLBACK.add_to(parser)

# ------------------------------------------------------------------------------------------
# Compression
# ------------------------------------------------------------------------------------------

RATE = Setting("rate", float, REQUIRED, "fraction of filters to remove per layer, in [0, 1)", label="pruning rate",
               check=lambda v: 0 <= v < 1, requirement="in [0, 1) (e.g. 0.7 for 70%)")
METHOD = Setting("method", str, "l1", "l1: filter surgery (the paper); magnitude: tfmot unstructured sparsity",
                 label="method", choices=("l1", "magnitude"))
STRATEGY = Setting("strategy", str, "independent",
                   "L1 ranking on the original kernels, or after removing pruned inputs (Li et al.)",
                   label="strategy", choices=("independent", "greedy"))
IMPORTANCE = Setting(
    "importance", str, "l1",
    "how filters are ranked before surgery: l1 (kernel L1 norm, the paper's), l2 (kernel L2 norm), activation "
    "(mean |output| over training frames), taylor (|output x gradient| of the training loss over training frames; "
    "docs/compression.md)", label="importance criterion", choices=("l1", "l2", "activation", "taylor"))
"""The library's (`prune_model`, `CompressOptions`) and the sweep's default: the paper's L1 norm, so the
sweep reproduces the paper's tables."""
COMPRESS_IMPORTANCE = IMPORTANCE.variant(
    default=None,
    help="how filters are ranked before surgery: taylor (default with the independent strategy: |output x gradient| "
         "of the training loss on training frames), l1 (kernel L1 norm, the paper's; the default with --strategy "
         "greedy or --method magnitude), l2 (kernel L2 norm), activation (mean |output| on training frames); "
         "docs/compression.md")
"""`compress` serves a user's model: Taylor ranking keeps finer keypoints than the paper's L1 at 70 % for about one
retraining epoch of scoring (docs/compression.md, "Importance criteria and distillation"); `--importance l1` is the
paper's."""
DEFAULT_COMPRESS_IMPORTANCE = "taylor"
"""What `compress --importance` resolves to for filter surgery with the independent strategy."""
MIN_FILTERS = Setting(
    "min_filters", int, 0,
    "no pruned layer narrower than N filters (all of a layer that has fewer); the other layers are pruned harder so "
    "the network has no more parameters than at --rate with the paper's per-layer rule; 0 is the paper's rule",
    label="narrowest layer", check=lambda v: v >= 0, requirement="a whole number >= 0", metavar="N")
"""The library's (`prune_model`, `CompressOptions`) and the sweep's default: every layer keeps n - floor(n x rate)
filters, the paper's widths and parameter counts."""
DEFAULT_COMPRESS_MIN_FILTERS = 15
"""What `compress --min-filters` resolves to for filter surgery (magnitude pruning keeps every filter). The keep
rule leaves FCN-Pose's conv5 and conv6 with 3 filters at 0.7, through which every keypoint's position passes; with
no layer under 15 filters the same parameter budget goes to the bottleneck and conv1/conv2 get narrower (fewer MACs,
finer keypoints; the comparisons with the paper's widths and with 12: docs/compression.md, "The narrowest layer")."""
COMPRESS_MIN_FILTERS = MIN_FILTERS.variant(
    default=None,
    help=f"no pruned layer narrower than N filters (all of a layer that has fewer), the other layers pruned harder "
         f"so the network has no more parameters than the paper's per-layer rule gives at --rate (default: "
         f"{DEFAULT_COMPRESS_MIN_FILTERS} for filter surgery; 0 is the paper's rule, with which FCN-Pose's conv5 and "
         f"conv6 keep 3 filters at 0.7; docs/compression.md)")
"""`compress` moves the parameter budget from the wide high-resolution layers to the hourglass's bottleneck."""
IMPORTANCE_FRAMES = Setting(
    "importance_frames", int, 256, "with --importance activation or taylor: training frames (seeded choice, never "
    "the measured frames) the unpruned model is run on to score its filters", label="importance frames",
    check=lambda v: v >= 1, requirement="at least 1", metavar="N")
MORE_FRAMES = Setting(
    "more_frames", str, None, "a video or an image folder of your camera: up to --more-frames-count of its frames "
    "(evenly spread), labelled by --model, are added to the retraining's training frames (never to validation), and "
    "the time budgets left at their defaults grow with the frames; a VIA project (.json, one --more-frames-via kept, "
    "corrected or not) adds its frames with their labels as they are (docs/compression.md, \"More frames of your "
    "look\")", label="--more-frames", check=lambda v: bool(v.strip()),
    requirement="a video file, an image folder or a VIA .json project", metavar="SOURCE")
"""The lever that kept a 70 % network within 0.02 PCK@0.5 of its unpruned model on a look it was never pretrained on
(720 frames labelled by the model beside the user's 192, 45 minutes of retraining); none by default: it costs the
minutes."""
MORE_FRAMES_COUNT = Setting(
    "more_frames_count", int, 720, "--more-frames: at most this many frames, evenly spread over the source (the first "
    "and the last among them; a video that does not say its length gives its first N)", label="--more-frames-count",
    check=lambda v: v >= 1, requirement="at least 1", metavar="N")
"""The count measured: 720 frames gained 0.04 PCK@0.5 in 45 minutes; 240 in 25 minutes gained nothing
(docs/results.md)."""
POLISH_MINUTES = Setting(
    "polish_minutes", float, 10.0, "--more-frames: after the retraining on your frames and the added ones, retrain "
    "this many minutes more on your own labelled frames alone, at a tenth of the learning rate (conv1-2 fixed with "
    "filter surgery), the retrained model the epoch to beat (--keep-best); the total budget grows by them; 0: none",
    label="--polish-minutes", check=lambda v: v >= 0, requirement=">= 0", metavar="M")
"""Frames a model labelled carry its errors: a network retrained on them places keypoints less finely than on the
user's own labels, and a short retraining on those alone afterwards gives the fine placement back (docs/compression.md,
"More frames of your look")."""
POLISH_LEARNING_RATE_SCALE = 0.1
"""The polish's learning rate: the retraining's times this (3e-4 after compress's 3e-3)."""
MORE_FRAMES_VIA = Setting(
    "more_frames_via", str, None, "--more-frames: keep the frames the model labelled as this VIA project (a video's "
    "frames saved as PNGs in images/ beside it), to look at, correct, and pass back as --more-frames OUT.json; kept "
    "also when a later step fails (default: a temporary folder, removed)", label="--more-frames-via",
    check=lambda v: v.lower().endswith(".json"), requirement="a .json file", metavar="OUT.json")
"""None by default: a video's 720 frames as PNGs are hundreds of megabytes a user asks for."""
PRUNED_START = Setting(
    "start", str, "auto",
    "the pruned network's weights before retraining: surgery (the base model's highest-ranked filters, the paper's), "
    "generalist-p70 (the bundled generalist pruned at 0.7 and retrained on domain-randomised frames), or a pruned "
    ".keras file with the widths surgery gives at --rate; auto: generalist-p70 when the model to compress is the "
    "generalist as it is (the bundled file, or a model `train` kept unchanged from it: views that vary where no epoch "
    "beat it) and the widths match, else surgery. A pruned start is kept unchanged when no retraining epoch beats its "
    "validation loss (docs/compression.md, \"On your own model\")", label="pruned start",
    check=lambda v: bool(v.strip()), requirement="auto, surgery, a bundled name or a .keras file", metavar="START",
    paper="surgery")
"""Where the 70 % network's weights start. auto by default: the bundled pruned generalist is the better start for the
generalist itself, surgery for everything else measured (docs/compression.md, "On your own model";
`methods.pruned_start`)."""
COMPRESS_INPUT_SIZE = INPUT_SIZE.variant(
    default=None, paper=None,
    help=f"the input side the compressed model and files run at, a multiple of {INPUT_SIZE_MULTIPLE}: FCN-Pose is "
         "fully convolutional, so the model is rebuilt at this size with its weights, pruned, retrained and exported "
         "at it, and the files are named NAME_p70_SIZE; a smaller side costs fewer MACs (192: 0.73x of 224's) and "
         "localises coarser (docs/compression.md, \"A smaller input\"); for a model whose input is H x W, the height, "
         "the width following at the same aspect (a multiple of 32), the crop kept (default: the model's own, or the "
         "height a pruned --start was retrained at when the frame is not cropped, 256 for generalist-p70, the files "
         "named NAME_p70)")
"""None keeps the model's own size (the paper's protocol), or takes a pruned start's (`methods.start_height`); the sweep
always keeps it (each fold's base at its size, surgery)."""
EXPORT_INPUT_SIZE = COMPRESS_INPUT_SIZE.variant(
    help=f"the input side the files run at, a multiple of {INPUT_SIZE_MULTIPLE} (default: the model's own): the model "
         "rebuilt at this size with its weights, nothing retrained, the files named NAME_SIZE_fp16.tflite; for `run "
         "--track`, whose crop about the arm gives a smaller input the pixels the whole frame gave a larger one "
         "(docs/runtime.md, \"A crop that follows the arm\"); for an H x W input, the height, the width following")
DISTILL = Setting(
    "distill", float, 0.0,
    "weight W of the unpruned model's maps while retraining: loss = (1 - W) x loss against the ground-truth maps "
    "+ W x loss against the teacher's maps on the same augmented frames; 0 (default) retrains on the ground truth "
    "alone, as the paper does", label="distillation weight", check=lambda v: 0 <= v <= 1,
    requirement="a number in [0, 1]", metavar="W")
"""0 keeps the paper's retraining loss exactly; docs/compression.md measures other weights."""
@dataclasses.dataclass(frozen=True)
class TFLiteFormat:
    """One TFLite format `--quantize` names: its file, its keypoint gate, its conversion's needs.

    The gate (`fcnpose_tf.compression.export`) compares the file's maps with the Keras model's within `map_atol`
    and its keypoints within `keypoint_px` map pixels, on at least `min_frames` real frames, where `keypoint_share`
    of the keypoints compared must agree (a keypoint lost or gained always fails); `calibrated` formats need
    calibration frames; `fold_upsampling` is whether the export rewrites the decoder's upsampling by default."""

    name: str
    file_tag: str
    """The TFLite file name's suffix: NAME_p70_fp16.tflite."""
    map_atol: float
    keypoint_px: float
    keypoint_share: float
    min_frames: int
    calibrated: bool = False
    fold_upsampling: bool = False
    output_rtol: float = 1e-2
    """A model that is not a keypoint model (a classifier, any CNN): the largest |tflite - keras| over its outputs,
    relative to the output's scale (1 for probabilities, else the largest |output|; `compression.verify`)."""
    top1_share: float = 1.0
    """A classifier's (outputs N x K): the share of the compared samples whose top-1 class must agree."""


TFLITE_FORMATS = {f.name: f for f in (
    TFLiteFormat("float32", "fp32", map_atol=1e-2, keypoint_px=1.0, keypoint_share=1.0, min_frames=1,
                 output_rtol=1e-3),
    TFLiteFormat("float16", "fp16", map_atol=1e-2, keypoint_px=1.0, keypoint_share=1.0, min_frames=1),
    TFLiteFormat("int8-weights", "int8w", map_atol=0.2, keypoint_px=2.0, keypoint_share=1.0, min_frames=1,
                 output_rtol=0.1, top1_share=0.9),
    TFLiteFormat("int8", "int8", map_atol=1.0, keypoint_px=2.0, keypoint_share=0.95, min_frames=16, calibrated=True,
                 fold_upsampling=True, output_rtol=0.1, top1_share=0.9),
    TFLiteFormat("float16-native", "fp16native", map_atol=1e-2, keypoint_px=1.0, keypoint_share=1.0, min_frames=1),
)}
"""The one table of TFLite formats (why each gate is what it is: docs/compression.md, "Verification"): float32, float16
weights (the paper's), dynamic-range int8 weights, full-integer int8 (int8 weights and activations, uint8 pixel
input; the fastest on a Pi 3/4), and float16 with the converter's reduced-precision metadata (computed in float16
on CPUs with float16 arithmetic, a Pi 5)."""
QUANTIZE_MODES = tuple(TFLITE_FORMATS)
"""The formats' names, in the table's order."""
QUANTIZE_FILE_TAGS = {name: f.file_tag for name, f in TFLITE_FORMATS.items()}
"""A TFLite file name's suffix per format: NAME_p70_fp16.tflite, NAME_p70_int8.tflite."""


def quantize_modes(text: str) -> tuple[str, ...]:
    """argparse type of `compress --quantize`: one or more of QUANTIZE_MODES separated by commas, one file each."""
    modes: list[str] = []
    for part in str(text).split(","):
        mode = part.strip()
        if mode not in QUANTIZE_MODES:
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected one or more of {', '.join(QUANTIZE_MODES)} separated by commas, e.g. float16,int8")
        if mode not in modes:
            modes.append(mode)
    return tuple(modes)


QUANTIZE = Setting(
    "quantize", tuple, ("float16", "int8"),
    "TFLite files to write, one per format, comma-separated: float16 (the paper's), int8 (full integer, calibrated "
    "on training frames; the fastest on a Raspberry Pi 3/4), float32, int8-weights (dynamic range), "
    "float16-native (float16 with reduced-precision metadata: computed in float16 on a Raspberry Pi 5)",
    label="quantize", metavar="MODE[,MODE]", parse=quantize_modes, paper=("float16",),
    check=lambda v: isinstance(v, (tuple, list)) and len(v) > 0 and all(m in QUANTIZE_MODES for m in v)
    and len(set(v)) == len(v),
    requirement=f"a non-empty list of distinct formats out of {', '.join(QUANTIZE_MODES)}")
"""`compress` writes the paper's float16 file and the int8 file, so its table puts both in front of the user;
the paper's preset writes its float16 file only."""
CALIBRATION_FRAMES = Setting(
    "calibration_frames", int, 100, "int8: training frames (seeded choice, never the measured frames) the "
    "activation ranges are calibrated on", label="calibration frames", check=lambda v: v >= 1,
    requirement="at least 1", metavar="N")
CALIBRATION_SEED = SEED.variant(help="seed of the choice of int8 calibration frames")
"""`export` trains nothing: its only random choice is which training frames calibrate an int8 file
(`compress` draws them with its --seed)."""

# Quantization-aware training: compress's int8 fallback (fcnpose_tf.compression.qat; docs/compression.md, "int8 on a user's model").
QAT_EPOCHS = Setting(
    "qat_epochs", int, 4, "when post-training int8 is refused by its keypoint gate: at most N epochs of "
    "quantization-aware training (tfmot) from the retrained model on the same training frames, the int8 file "
    "converted and verified before the first (calibrated ranges) and after each; 0 = no fallback (the int8 row "
    "shows the refusal)", label="QAT epochs",
    check=lambda v: v >= 0, requirement="a whole number >= 0", metavar="N")
QAT_LEARNING_RATE = Setting(
    "qat_learning_rate", float, 1e-4, "Adam's learning rate of quantization-aware training",
    label="QAT learning rate", check=lambda v: 0 < v < 1, requirement="a number in (0, 1)", metavar="LR")
