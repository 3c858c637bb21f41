"""The paper's keep rule and the ranking: how many filters a layer keeps at a rate, and which.

Rates are fractions in [0, 1) of the filters to *remove*. The keep rule is the paper's (and NNI's),
``n - floor(n * rate)``, which always keeps at least one filter; Torch-Pruning's ``floor(n * (1 - rate))`` keeps one
fewer whenever ``n * rate`` is not a whole number. Rates are read exactly (the shortest decimal that prints as the
float: 0.29 -> 29/100) once per call (`exact_rate`), and the per-layer arithmetic takes the exact rate
(`exact_keep_count`). `floored_widths` is the rule with a floor (`--min-filters`) at the same parameter budget.
The filters kept are those an importance score ranks highest (`fcnpose_tf.compression.importance`), ties to the
lower index, in their original order. Chain surgery (`prune`) and graph surgery (`depgraph`) both count with it.
"""

from __future__ import annotations

import math
import numbers
from decimal import Decimal
from fractions import Fraction
from typing import Callable, Iterable, Sequence, Union

import numpy as np

from fcnpose_tf.compression.importance import WeightNorm
from fcnpose_tf.errors import UserError

Rate = Union[float, int, Fraction, Decimal, str]
"""A pruning rate: a float, a fraction, a decimal or its text."""

# Slack added to n * rate before flooring, for rates computed in floating point (0.1 * 7 and the
# like). Rates are first read exactly as the shortest decimal that prints as the float (0.29 ->
# 29/100), so a typed rate never needs it.
_RATE_SLACK = Fraction(1, 10**9)


def exact_rate(rate: Rate) -> Fraction:
    """The rate as an exact fraction: how every function here reads its rate, once per call, before any per-layer
    arithmetic (`exact_keep_count`).

    Args:
        rate: fraction of filters to remove, in [0, 1); a float (read as the shortest decimal that prints as it:
            0.29 -> 29/100), int, Fraction, Decimal or a decimal string such as ``"0.7"``.
    Returns:
        The fraction.
    Raises:
        UserError: a rate outside [0, 1) or not a number.
    """
    if isinstance(rate, bool):
        raise UserError(f"pruning rate must be a number in [0, 1), got {rate!r}")
    try:
        if isinstance(rate, str):
            value = Fraction(rate.strip())
        elif isinstance(rate, (Fraction, int)):
            value = Fraction(rate)
        elif isinstance(rate, Decimal):
            if not rate.is_finite():
                raise ValueError
            value = Fraction(rate)
        elif isinstance(rate, numbers.Real):
            if not math.isfinite(float(rate)):
                raise ValueError
            # repr of a float is the shortest decimal that reads back as it: 0.29 -> "0.29" -> 29/100.
            value = Fraction(repr(float(rate)))
        else:
            raise ValueError
    except (ValueError, ZeroDivisionError):
        raise UserError(f"pruning rate must be a number in [0, 1), got {rate!r}") from None
    if not 0 <= value < 1:
        raise UserError(f"pruning rate must be in [0, 1) (the fraction of filters removed), got {rate!r}")
    return value


def keep_count(n: int, rate: Rate) -> int:
    """Filters a layer of `n` filters keeps at `rate`: ``n - floor(n * rate)``, at least 1.

    The product is computed exactly (the rate is read as the decimal it prints as), so
    ``keep_count(100, 0.29) == 71`` although ``100 * 0.29`` is 28.999999999999996 in floating point.

    Args:
        n: the layer's filter count (positive).
        rate: fraction of filters to remove, in [0, 1); a float, int, Fraction, Decimal or a
            decimal string such as ``"0.7"``.
    Returns:
        The number of filters kept.
    Raises:
        UserError: if the rate is outside [0, 1) or not a number, or n is not positive.
    Example:
        >>> keep_count(128, 0.7), keep_count(8, 0.7), keep_count(64, 0.5)
        (39, 3, 32)
    """
    return exact_keep_count(_filter_count(n), exact_rate(rate))


def exact_keep_count(n: int, rate: Fraction) -> int:
    """`keep_count` on a rate `exact_rate` read and a positive filter count: the per-layer arithmetic, nothing checked.

    Args:
        n: the layer's filter count (positive).
        rate: the exact rate, in [0, 1).
    Returns:
        The number of filters kept, ``n - floor(n * rate)``, at least 1.
    """
    removed = math.floor(n * rate + _RATE_SLACK)
    return n - min(int(removed), n - 1)


def _filter_count(n: int) -> int:
    """`n` as a filter count; UserError unless a positive integer."""
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise UserError(f"filter count must be a positive integer, got {n!r}")
    return int(n)


def pruned_widths(widths: Iterable[int], rate: Rate) -> tuple[int, ...]:
    """The keep rule applied to each width, e.g. FCN-Pose's conv1..conv9 (not the output layer).

    Args:
        widths: filter counts of the layers that are pruned.
        rate: fraction of filters to remove, in [0, 1).
    Returns:
        The kept filter counts, in the same order.
    Raises:
        UserError: for a rate outside [0, 1) or a non-positive width.
    Example:
        >>> pruned_widths((128, 64, 32, 16, 8, 8, 16, 32, 64), 0.7)
        (39, 20, 10, 5, 3, 3, 5, 10, 20)
    """
    return _kept_widths(widths, exact_rate(rate))


def _kept_widths(widths: Iterable[int], rate: Fraction) -> tuple[int, ...]:
    """`pruned_widths` at a rate `exact_rate` read: each width checked, the rate not again."""
    return tuple(exact_keep_count(_filter_count(int(w)), rate) for w in widths)


def filter_l1_norms(kernel: np.ndarray, input_channels: Sequence[int] | None = None) -> np.ndarray:
    """L1 norm of every filter of a Conv2D kernel (kh, kw, cin, cout): sum of |w| over kh, kw and cin.

    Args:
        kernel: the Conv2D kernel, shape (kh, kw, cin, cout).
        input_channels: if given, only these input channels count (the greedy strategy leaves out
            the channels the previous layer lost).
    Returns:
        A float64 array of length cout.
    """
    return WeightNorm(1).filter_scores(kernel, input_channels)


def kept_filters(kernel: np.ndarray, rate: Rate, input_channels: Sequence[int] | None = None) -> np.ndarray:
    """Indices of the filters a Conv2D keeps at `rate`: the largest L1 norms, in their original order.

    Ties in the norm go to the lower index, so the choice is deterministic.

    Args:
        kernel: the Conv2D kernel, shape (kh, kw, cin, cout).
        rate: fraction of filters to remove, in [0, 1).
        input_channels: rank only on these input channels (the greedy strategy); all if None.
    Returns:
        Sorted int64 indices, ``keep_count(cout, rate)`` of them.
    Raises:
        UserError: for a rate outside [0, 1) or a kernel that is not 4-D.
    Example:
        >>> k = np.zeros((1, 1, 1, 4)); k[..., :] = [3.0, -5.0, 1.0, 3.0]
        >>> kept_filters(k, 0.5).tolist()
        [0, 1]
    """
    return kept_by_score(filter_l1_norms(kernel, input_channels), rate)


def kept_by_score(scores: np.ndarray, rate: Rate) -> np.ndarray:
    """Indices of the ``keep_count(len(scores), rate)`` highest scores, in their original order.

    Ties go to the lower index, so the choice is deterministic.

    Args:
        scores: one score per filter.
        rate: the pruning rate.
    Returns:
        The kept indices (int64).
    Raises:
        UserError: scores that are not a finite 1-D array.
    Example:
        >>> kept_by_score(np.array([0.2, 0.9, 0.2, 0.5]), 0.5).tolist()
        [1, 3]
    """
    return kept_top(scores, keep_count(len(np.atleast_1d(scores)), rate))


def kept_top(scores: np.ndarray, count: int) -> np.ndarray:
    """Indices of the `count` highest scores, in their original order; ties go to the lower index.

    Args:
        scores: one score per filter.
        count: how many to keep.
    Returns:
        The kept indices (int64).
    Raises:
        UserError: scores that are not a finite 1-D array, or more to keep than there are.
    Example:
        >>> kept_top(np.array([0.2, 0.9, 0.2, 0.5]), 3).tolist()
        [0, 1, 3]
    """
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 1 or not np.all(np.isfinite(scores)):
        raise UserError(f"filter scores must be a finite 1-D array, got shape {scores.shape}")
    if not 1 <= count <= len(scores):
        raise UserError(f"a layer of {len(scores)} filters cannot keep {count}")
    # Stable sort on the negated scores: largest first, equal scores in index order.
    order = np.argsort(-scores, kind="stable")
    return np.sort(order[:count]).astype(np.int64)


def floored_widths(widths: Sequence[int], rate: Rate, min_filters: int,
                   param_count: Callable[[tuple[int, ...]], int]) -> tuple[tuple[int, ...], int]:
    """Kept filter counts that leave no layer narrower than `min_filters`, at no more parameters than the keep rule's.

    The keep rule at `rate` leaves the narrow layers of an hourglass network (FCN-Pose's conv5 and conv6: 8
    filters) with 3 filters at 0.7, through which every keypoint's position has to pass. Here every layer keeps
    at least ``min(n, min_filters)`` filters and the others are pruned at the smallest rate >= `rate` at which the
    whole network has no more parameters than ``pruned_widths(widths, rate)`` gives it: the budget moves from the
    wide, high-resolution layers to the bottleneck. If no rate fits the budget with that floor (high rates), the
    floor is lowered one filter at a time; a floor of 1 is the keep rule itself.

    Args:
        widths: filter counts of the layers that are pruned, in order.
        rate: fraction of filters to remove, in [0, 1); sets the parameter budget.
        min_filters: the narrowest a layer may become (0 or 1: the plain keep rule).
        param_count: the network's parameter count for a tuple of kept counts (`chain_param_count`).
    Returns:
        (kept counts, the floor used).
    Example:
        >>> count = lambda kept: sum(kept)  # a toy cost: one parameter per filter
        >>> floored_widths((128, 64, 8), 0.7, 4, count)
        ((38, 19, 4), 4)
    """
    start = exact_rate(rate)
    uniform = _kept_widths(widths, start)
    if isinstance(min_filters, bool) or not isinstance(min_filters, numbers.Integral) or min_filters < 0:
        raise UserError(f"the narrowest layer width must be a whole number >= 0, got {min_filters!r}")
    if all(k >= min(n, min_filters) for n, k in zip(widths, uniform)):  # always so for a floor of 0 or 1
        return uniform, int(min_filters)
    budget = param_count(uniform)
    # Keep counts only change at rates m/n, so these are all the rates worth trying, in increasing order.
    rates = sorted({start} | {Fraction(m, n) for n in set(widths) for m in range(1, n) if Fraction(m, n) > start})
    for floor in range(int(min_filters), 1, -1):
        for candidate in rates:
            kept = tuple(max(exact_keep_count(int(n), candidate), min(n, floor)) for n in widths)
            if param_count(kept) <= budget:
                return kept, floor
    return uniform, 1
