"""How filters or weights are removed: one `PruningMethod` interface, one object per method.

`FilterPruning` is the paper's exact layer surgery (`fcnpose_tf.compression.prune`), its filters ranked by an
importance criterion (`fcnpose_tf.compression.importance`) or its widths taken from a pruned start
(`pruned_start`); `MagnitudePruning` is tfmot's weight masking. Both retrain through `train.fit`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Protocol, TypedDict

from fcnpose_tf.compression.report import PruningSections
from fcnpose_tf.errors import UserError
from fcnpose_tf.progress import SILENT, Reporter
from fcnpose_tf.records import training_record

if TYPE_CHECKING:
    import tf_keras as keras

    from fcnpose_tf.compression.importance import Importance
    from fcnpose_tf.compression.options import CheckedOptions, CompressOptions
    from fcnpose_tf.compression.plan import WidthPlan
    from fcnpose_tf.training.train import FitResult

FitFn = Callable[..., "FitResult"]
"""`fit_fn(model, callbacks=(), inference_model=None)`: the retraining `fit`, writing NAME_pXX.keras."""


class MethodRecord(TypedDict, total=False):
    """What a retrained model's NAME_train.json says about the method that pruned it (`Pruned.record`), in this
    order: filter surgery its rate, strategy (or pruned start), min_filters and criterion; magnitude pruning its rate,
    method and sparsity."""

    rate: float
    method: str
    """"magnitude" (filter surgery names none)."""
    sparsity: float
    """Magnitude pruning's fraction of zeroed weights."""
    start: str
    """A pruned start's name (filter surgery from a pruned model's weights)."""
    strategy: str
    """Filter surgery's ranking strategy (independent, greedy)."""
    min_filters: int
    importance: str
    """The filter criterion (`importance.Importance.describe`; none for a pruned start)."""
    importance_frames: int
    """Frames a data-aware criterion scored the filters on."""


class Pruned(NamedTuple):
    """What `PruningMethod.prune` returns: the pruned model and what the report and the retraining record say of it."""

    model: keras.Model
    """The pruned model before retraining."""
    sections: PruningSections
    """The report sections the method adds (pruning, magnitude_sparsity)."""
    record: MethodRecord
    """What the retraining's NAME_train.json says about the method."""


class PruningMethod(Protocol):
    """How a method prunes the base model and retrains the result through the same `fit`."""

    name: str
    start_name: str
    """Where the pruned network's weights come from: "surgery" (the base model's, cut), or a pruned start's name."""
    words: str
    """The progress line's words for what is pruned, e.g. "filter surgery at rate 0.7 (no layer under 15 filters),
    filters ranked by taylor (independent)"."""
    recipe: str
    """One line naming how the file is made, the report's and the retraining record's "recipe": the pruning (the plan's
    rate and floor, the start or the criterion) and the retraining (`retraining_words`)."""

    @property
    def ranks_filters(self) -> bool:
        """Whether `prune` ranks the base model's filters by an `Importance` (else it is passed None)."""

    @property
    def trained_start(self) -> bool:
        """Whether `prune` returns trained weights of the pruned network (a pruned start), whose validation loss the
        retraining must beat: if no epoch does, the start is kept unchanged (`train.fit`'s start_is_candidate)."""

    def prune(self, base: keras.Model, importance: Importance | None) -> Pruned:
        """Prune the base model (not changed) by the run's plan.

        Args:
            base: the model to prune, at the run's input size.
            importance: the criterion filters are ranked by (`ranks_filters`), else None.
        Returns:
            The pruned model before retraining, the report sections the method adds (pruning, magnitude_sparsity)
            and the retraining record's `MethodRecord`.
        Raises:
            UserError: a pruned start that is not this plan's network.
        """

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        """Retrain the pruned model with `fit_fn`, which saves the retrained model for inference.

        Args:
            base: the unpruned model (magnitude pruning's masks are computed from its weights).
            pruned: what `prune` returned.
            fit_fn: the run's retraining (`FitFn`).
        """


class FilterPruning:
    """The paper's method: remove the least important filters (exact layer surgery); the paper ranks them by
    L1 norm, `fcnpose_tf.compression.importance` holds the other criteria. The method is named "l1" in reports and
    options for that reason; the criterion is recorded beside it. The widths are the run's `WidthPlan`.

    Args:
        plan: the run's widths (`plan.plan_widths`, with the options' floor).
        options: the run's options: strategy (`prune.STRATEGIES`), importance and importance_frames (the criterion's
            name and frames, for the words and the recipe; `prune` records the criterion's own facts), and the
            retraining's settings (the recipe).
        start: a pruned model whose weights the network takes instead of surgery on the base (`pruned_start`);
            None: surgery.
        start_name: the start's name for lines and records (default: its path).
    """

    name = "l1"

    def __init__(self, plan: WidthPlan, options: CompressOptions, start: Path | None = None,
                 start_name: str = "") -> None:
        from fcnpose_tf.compression.importance import DATA_AWARE

        self.plan, self.strategy, self.importance = plan, options.strategy, options.importance
        self.rate, self.min_filters = plan.rate, plan.floor
        self.start, self.start_name = start, start_name or str(start)  # a pruned model's weights (None: surgery)
        under = f" (no layer under {self.min_filters} filters" if self.min_filters > 1 else ""
        budget = "" if not under else ", same parameter budget)" if plan.floor == plan.min_filters else \
            f": --min-filters {plan.min_filters} lowered to fit the parameter budget)"
        frames = f", {options.importance_frames} training frames" if self.importance in DATA_AWARE else ""
        self.words = self._pruning(f"rate {self.rate:g}", under + (")" if under else ""), "")
        self.recipe = self._pruning(f"{self.rate:g}", under + budget, frames) + retraining_words(options)

    def _pruning(self, rate: str, floor: str, frames: str) -> str:
        """What is pruned, in the progress line's words or (with the floor's reason and the criterion's frames) the
        recipe's."""
        if self.start is not None:
            return f"filter surgery's widths at {rate}{floor}, the weights of {self.start_name}"
        return f"filter surgery at {rate}{floor}, filters ranked by {self.importance} ({self.strategy}{frames})"

    @property
    def ranks_filters(self) -> bool:
        """True for surgery on the base; a pruned start ranks nothing."""
        return self.start is None

    @property
    def trained_start(self) -> bool:
        """True with a pruned start."""
        return self.start is not None

    def prune(self, base: keras.Model, importance: Importance | None) -> Pruned:
        """Surgery on `base` at the plan's widths, the filters `importance` ranks highest kept; or the pruned start's
        weights in the network surgery would build.

        Args:
            base: the model to prune (not changed).
            importance: the criterion (None with a pruned start).
        Returns:
            The pruned model; the report's "pruning" section (criterion facts, strategy, min_filters,
            ranking_seconds; or the start's name and file, and min_filters); the record: the rate, the strategy (or
            the pruned start), min_filters (the plan's floor) and the criterion's facts.
        Raises:
            UserError: a pruned start of another network or other widths than the plan's.
        """
        from fcnpose_tf.compression.prune import prune_model

        if self.start is not None:
            return self._from_start(base)
        start = time.perf_counter()
        pruned = prune_model(base, self.rate, strategy=self.strategy, importance=importance,
                             min_filters=self.min_filters, widths=self.plan)
        facts = importance.describe()
        return Pruned(pruned, PruningSections(pruning={**facts, "strategy": self.strategy,
                                                       "min_filters": self.min_filters,
                                                       "ranking_seconds": round(time.perf_counter() - start, 1)}),
                      {"rate": self.rate, "strategy": self.strategy, "min_filters": self.min_filters, **facts})

    def _from_start(self, base: keras.Model) -> Pruned:
        """The start model's weights in the network surgery would build from `base` (same widths, the base's input
        size); UserError when its widths are not surgery's."""
        from fcnpose_tf.training.model import ARCHITECTURES, architecture_of, build_fcn_pose, conv_widths, load_model, \
            view_of

        source = load_model(self.start)
        widths = self.plan.widths
        if architecture_of(source) != architecture_of(base):
            raise UserError(f"--start {self.start_name}: an {architecture_of(source)} network, the model to compress "
                            f"an {architecture_of(base)} one")
        if conv_widths(source) != widths:
            floor = f" with no layer under {self.min_filters} filters" if self.min_filters > 1 else ""
            raise UserError(f"--start {self.start_name}: its widths {conv_widths(source)} are not filter surgery's at "
                            f"--rate {self.rate:g}{floor} on this model, {widths}")
        pruned = build_fcn_pose(widths[:-1], view_of(base), widths[-1], skip=ARCHITECTURES[architecture_of(base)])
        pruned.set_weights(source.get_weights())
        return Pruned(pruned, PruningSections(pruning={"start": self.start_name, "start_file": str(self.start),
                                                       "min_filters": self.min_filters}),
                      {"rate": self.rate, "start": self.start_name, "min_filters": self.min_filters})

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        """Retrain the pruned network itself (`fit_fn(pruned)`); `base` is not used.

        Args:
            base: not used.
            pruned: the network `prune` returned.
            fit_fn: the run's retraining.
        """
        fit_fn(pruned)


class MagnitudePruning:
    """tfmot's unstructured pruning, zeroing as many weights as L1 surgery at the plan's rate removes (the plan: the
    paper's keep rule, no floor).

    Args:
        plan: the run's widths at the rate, with no floor; its parameters set the sparsity.
        options: the run's options (the retraining's settings, for the recipe).
    """

    name = "magnitude"
    start_name = "surgery"
    ranks_filters = trained_start = False

    def __init__(self, plan: WidthPlan, options: CompressOptions) -> None:
        self.rate, self.plan = plan.rate, plan
        self.sparsity = 0.0
        self.words = f"magnitude at rate {self.rate:g}"
        self.recipe = f"magnitude pruning at {self.rate:g}" + retraining_words(options)

    def prune(self, base: keras.Model, importance: Importance | None) -> Pruned:
        """Zero the smallest weights of `base`'s kernels (a copy), as many as filter surgery's plan removes.

        Args:
            base: the model to prune (not changed).
            importance: not used (magnitude pruning ranks weights, not filters).
        Returns:
            The masked model, the report's "magnitude_sparsity" (1 - plan parameters / base parameters), and the
            record: the rate, the method ("magnitude") and the sparsity.
        """
        from fcnpose_tf.compression.magnitude import magnitude_prune

        self.sparsity = 1.0 - self.plan.params / base.count_params()  # the same reduction as filter surgery
        sparsity = round(self.sparsity, 6)
        return Pruned(magnitude_prune(base, self.sparsity), PruningSections(magnitude_sparsity=sparsity),
                      {"rate": self.rate, "method": self.name, "sparsity": sparsity})

    def retrain(self, base: keras.Model, pruned: keras.Model, fit_fn: FitFn) -> None:
        """Retrain `base` under the masks `prune` computed (tfmot keeps them while `fit_fn` trains; the file saved is
        stripped of the wrappers); `pruned` is not used: the masks are made again from `base`'s weights.

        Args:
            base: the unpruned model, wrapped and retrained under the masks.
            pruned: not used.
            fit_fn: the run's retraining.
        """
        import tensorflow_model_optimization as tfmot

        from fcnpose_tf.compression.magnitude import magnitude_prune

        # the same masks as `prune` (computed from the base's weights), kept while fit retrains
        magnitude_prune(base, self.sparsity, train_fn=lambda wrapped, callbacks: fit_fn(
            wrapped, callbacks=callbacks, inference_model=tfmot.sparsity.keras.strip_pruning))


PRUNED_GENERALIST = "generalist-p70"
"""The bundled pruned generalist (`bundled.BUNDLED_MODELS`): `--start auto`'s choice for a model fine-tuned from the
generalist, at the widths it has (filter surgery's at 0.7 with compress's default floor, no layer under 15 filters)."""


def holds_the_generalist(model_path: str | os.PathLike, generalist: Path) -> bool:
    """Whether `model_path` holds the generalist's own weights: it is the bundled file (`generalist`, resolved), or
    `train` kept its start unchanged, through as many kept rounds as there are (`records.lineage`, kept_only), back to
    the generalist.

    Args:
        model_path: the model to compress.
        generalist: the bundled generalist's file, resolved.
    Returns:
        True for the generalist as it is; False for a model trained from it, or from anything else.
    """
    from fcnpose_tf.records import lineage

    return any(name == "generalist" or (Path(name).is_file() and Path(name).resolve() == generalist)
               for name in [str(model_path), *lineage(model_path, kept_only=True)])


def pruned_start(checked: CheckedOptions, base_path: Path, plan: WidthPlan, architecture: str,
                 reporter: Reporter = SILENT) -> tuple[str, Path | None]:
    """The run's pruned start, the options' start with auto decided. auto is PRUNED_GENERALIST when `base_path` holds
    the generalist's own weights (`holds_the_generalist`: the bundled file, or a model `train` kept unchanged from it)
    on views that vary (its record's augmentation is online) and the bundled file has the base's architecture
    (`model.ARCHITECTURES`) and the widths filter surgery gives here (`plan`): there it is the same network pruned and
    retrained for hours on domain-randomised frames, where surgery retrains on the user's few. Else surgery: on a
    model fine-tuned from the generalist the pruned generalist measured below it, and on fixed-camera models surgery
    keeps PCK@0.5 within 0.01 (docs/compression.md, "On your own model"). An explicit start is the file the options'
    check found (`CheckedOptions.start_file`); its widths are checked when it is loaded (`FilterPruning.prune`). The
    run then takes the start's input height (`start_height`).

    Args:
        checked: the run's options (method and start) and the explicit start's file.
        base_path: the model being compressed.
        plan: the run's widths.
        architecture: the base model's network (`model.ARCHITECTURES`).
        reporter: where a fallback to surgery is said, and a bundled start's file named.
    Returns:
        (the start's name, the pruned model file it names; None for surgery).
    """
    from fcnpose_tf.bundled import BUNDLED_MODELS, generalist_model, models_dir, say_bundled
    from fcnpose_tf.training.model import architecture_of, conv_widths, load_model

    options = checked.options
    start = options.start
    if options.method != "l1" or start == "surgery":
        return "surgery", None
    if start != "auto":
        say_bundled(start, checked.start_file, reporter)
        return start, checked.start_file
    if not holds_the_generalist(base_path, generalist_model().resolve()):
        return "surgery", None
    record = training_record(base_path)
    if record is None or record.augment != "online":  # a fixed camera: the frames show the views it will see
        return "surgery", None
    path = models_dir() / BUNDLED_MODELS[PRUNED_GENERALIST][0]
    if not path.is_file():  # an installation without it
        reporter.say(f"  pruned start: surgery (the bundled {PRUNED_GENERALIST}, {path}, is missing)")
        return "surgery", None
    bundled = load_model(path)
    if architecture_of(bundled) != architecture:
        reporter.say(f"  pruned start: surgery ({PRUNED_GENERALIST} is an {architecture_of(bundled)} network, "
                     f"{base_path} an {architecture} one)")
        return "surgery", None
    if conv_widths(bundled) != plan.widths:
        reporter.say(f"  pruned start: surgery ({PRUNED_GENERALIST}'s widths are not filter surgery's at rate "
                     f"{options.rate:g} with no layer under {plan.floor} filters, {plan.widths})")
        return "surgery", None
    return PRUNED_GENERALIST, path


def start_height(start: Path | None, base: keras.Model, options: CompressOptions) -> int | None:
    """The input height a run takes from its pruned start: the height the start was retrained at (the bundled
    generalist-p70's 256), when no --input-size is given, neither model crops the frame and the base's height is
    another. A pruned start's weights learnt the arm at its own pixel density: on random views the 70 % generalist
    retrained at 256 stays within 0.02 PCK@0.5 and 0.03 PCK@0.05 of the unpruned model where the same network at 224
    loses 0.04-0.06 PCK@0.05 (docs/compression.md, "On your own model").

    Args:
        start: the pruned start's file (`pruned_start`; None: surgery, the base's own height).
        base: the model to compress, as loaded.
        options: the run's options (`input_size`: the user's height, which wins).
    Returns:
        The height to rebuild the base at (its width following at its aspect: `model.at_input_height`), or None.
    """
    from fcnpose_tf.training.model import load_model, view_of

    if start is None or options.input_size:
        return None
    base_view, start_view = view_of(base), view_of(load_model(start))
    if base_view.crop is not None or start_view.crop is not None or start_view.height == base_view.height:
        return None
    return start_view.height


def pruning_method(options: CompressOptions, plan: WidthPlan, start_name: str = "surgery",
                   start: Path | None = None) -> PruningMethod:
    """The pruning method the options name.

    Args:
        options: the run's options (`CompressOptions.checked`'s).
        plan: the widths (`plan.plan_widths` at the options' rate, with their floor for filter surgery and none for
            magnitude pruning), at the run's input size.
        start_name: the pruned start as the run's options record it (`pruned_start`).
        start: its file (None: surgery).
    Returns:
        `FilterPruning` or `MagnitudePruning`; its `start_name` is the start the run's options record.
    """
    if options.method == "magnitude":
        return MagnitudePruning(plan, options)
    return FilterPruning(plan, options, start, start_name)


def retraining_words(options: CompressOptions) -> str:
    """The recipe's retraining part, as a method's recipe ends: the epochs, augmentation, loss, learning rate and frozen
    layers (or "not retrained"), and the input size the model was rebuilt at.

    Args:
        options: the run's options (resolved: `CompressOptions.checked`).
    Returns:
        The words, from their leading comma, e.g. ", retrained up to 25 epochs on binary cross-entropy, learning rate
        0.003, halved after 3 stale epochs".
    """
    from fcnpose_tf.training.train import loss_name

    size = f", at {options.input_size}x{options.input_size}" if options.input_size else ""
    if options.retrain_epochs == 0:
        return f", not retrained{size}"
    epochs = f"{options.retrain_epochs} epoch{'s' if options.retrain_epochs > 1 else ''}"
    rate = (f"learning rate {options.learning_rate:g} on a cosine" if options.lr_schedule == "cosine" else
            f"learning rate {options.learning_rate:g}, halved after {options.lr_patience} stale epochs"
            if options.lr_patience else f"learning rate {options.learning_rate:g}")
    frozen = f", conv1-{options.freeze} fixed" if options.freeze > 1 else ", conv1 fixed" if options.freeze else ""
    frames = " with online augmentation" if options.augment == "online" else ""  # the paper's copies: unsaid
    return (f", retrained up to {epochs}{frames} on {loss_name(options.positive_weight or 1.0, options.distill)}, "
            f"{rate}{frozen}{size}")
