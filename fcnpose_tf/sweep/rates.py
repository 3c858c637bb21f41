"""Pruning-rate specifications: `0.1:0.9:0.1`, `0.5,0.7`, `full,0.5` — exact, no float drift.

A rate is the fraction of filters removed from every pruned layer, in [0, 1), in whole
percentages (the paper steps by 10%); 0 (or `full`) is the unpruned model. Ranges are read as
decimals, so `0.1:0.9:0.1` is exactly the nine rates 0.1, 0.2, ..., 0.9, never 0.30000000000000004
or a missing end point.
"""

from __future__ import annotations

from decimal import ROUND_FLOOR, Decimal, InvalidOperation

from fcnpose_tf.errors import UserError

DEFAULT_RATES_SPEC = "0.1:0.9:0.1"
"""The paper's rates: 10% to 90% in 10% steps."""

FULL_WORDS = ("full", "none", "unpruned")
MAX_RATES = 100


def _number(text: str, spec: str) -> Decimal:
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise UserError(f"--rates {spec!r}: {text!r} is not a number (expected e.g. 0.1:0.9:0.1, 0.5,0.7 or "
                        "full,0.7)") from None
    if not value.is_finite():
        raise UserError(f"--rates {spec!r}: {text!r} is not a finite number")
    return value


def _check_rate(value: Decimal, text: str, spec: str) -> Decimal:
    if not 0 <= value < 1:
        hint = f"; write {value / 100} for {value}%" if 1 <= value < 100 else ""
        raise UserError(f"--rates {spec!r}: rate {text} is outside [0, 1) (the fraction of filters removed{hint})")
    if (value * 100) % 1:
        raise UserError(f"--rates {spec!r}: rate {text} is not a whole percentage (use steps of 0.01, e.g. 0.25)")
    return value


def _item(item: str, spec: str) -> list[Decimal]:
    if item.lower() in FULL_WORDS:
        return [Decimal(0)]
    if ":" not in item:
        return [_check_rate(_number(item, spec), item, spec)]
    parts = item.split(":")
    if len(parts) != 3 or not all(p.strip() for p in parts):
        raise UserError(f"--rates {spec!r}: range {item!r} must be START:STOP:STEP, e.g. 0.1:0.9:0.1")
    start, stop, step = (_number(p.strip(), spec) for p in parts)
    _check_rate(start, parts[0].strip(), spec)
    _check_rate(stop, parts[1].strip(), spec)
    if step <= 0:
        raise UserError(f"--rates {spec!r}: the step of {item!r} must be positive")
    if (step * 100) % 1:
        raise UserError(f"--rates {spec!r}: the step of {item!r} is not a whole percentage (e.g. 0.1 or 0.05)")
    if start > stop:
        raise UserError(f"--rates {spec!r}: range {item!r} starts above its stop")
    count = int(((stop - start) / step).to_integral_value(rounding=ROUND_FLOOR)) + 1
    return [start + i * step for i in range(count)]


def parse_rates(spec: str) -> tuple[float, ...]:
    """Read a rate specification into sorted, unique rates (0.0 stands for the unpruned model).

    Args:
        spec: comma-separated items, each a rate (``0.7``), a range ``START:STOP:STEP`` (STOP
            included when the steps land on it) or ``full`` (= 0, the unpruned model).
    Returns:
        The rates as floats that print as the decimals given (0.3, not 0.30000000000000004).
    Raises:
        UserError: for an empty spec, a non-number, a rate outside [0, 1), a rate or step that is
            not a whole percentage, a bad range, or more than 100 rates.
    Example:
        >>> parse_rates("0.1:0.9:0.1")
        (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
        >>> parse_rates("0.7, full, 0.5, 0.7")
        (0.0, 0.5, 0.7)
    """
    if not isinstance(spec, str) or not spec.strip():
        raise UserError("--rates is empty; expected e.g. 0.1:0.9:0.1, 0.5,0.7 or full,0.7")
    values: set[Decimal] = set()
    for raw in spec.split(","):
        item = raw.strip()
        if not item:
            raise UserError(f"--rates {spec!r}: empty item between commas")
        values.update(_item(item, spec))
    if len(values) > MAX_RATES:
        raise UserError(f"--rates {spec!r}: {len(values)} rates; at most {MAX_RATES}")
    return tuple(float(v) for v in sorted(values))


def rate_percent(rate: float) -> int:
    """The rate as a whole percentage (0.7 -> 70)."""
    return int(round(rate * 100))


def rate_tag(rate: float) -> str:
    """File tag of a rate, as `compress` names its outputs: 0.7 -> "p70", 0.05 -> "p05", 0 -> "p00"."""
    return f"p{rate_percent(rate):02d}"


def rate_label(rate: float | None) -> str:
    """Table label: "full" for the unpruned model (None or 0), else "70%"."""
    return "full" if rate is None or rate_percent(rate) == 0 else f"{rate_percent(rate)}%"


def parse_per_rate_epochs(spec: str | int, option: str = "--retrain-epochs") -> tuple[int, tuple[tuple[float, int], ...]]:
    """Read an epoch budget that may differ by rate: ``10`` or ``10,0.6:0.9:0.1=40``.

    Args:
        spec: comma-separated items: one plain count (the default for every rate) and any number
            of ``RATES=COUNT`` items, RATES being a rate or a range as `parse_rates` reads them.
        option: the option's name, for messages.
    Returns:
        (default, overrides): the overrides as sorted (rate, count) pairs, one per rate.
    Raises:
        UserError: no or two defaults, a count that is not a whole number >= 0, a bad rate, or a
            rate given two counts.
    Example:
        >>> parse_per_rate_epochs("10,0.6:0.7:0.1=40")
        (10, ((0.6, 40), (0.7, 40)))
    """
    if isinstance(spec, int):
        return spec, ()
    default: int | None = None
    overrides: dict[float, int] = {}
    for raw in str(spec).split(","):
        item = raw.strip()
        rates_text, sep, count_text = item.rpartition("=")
        try:
            count = int(count_text.strip())
        except ValueError:
            raise UserError(f"{option} {spec!r}: {count_text.strip()!r} is not a whole number of epochs (expected "
                            "e.g. 25 or 10,0.6:0.9:0.1=40)") from None
        if count < 0:
            raise UserError(f"{option} {spec!r}: epochs must be >= 0, got {count}")
        if not sep:
            if default is not None:
                raise UserError(f"{option} {spec!r}: two default epoch counts ({default} and {count}); give one, "
                                "then RATES=EPOCHS items")
            default = count
            continue
        try:
            rates = parse_rates(rates_text)
        except UserError as exc:
            raise UserError(str(exc).replace("--rates", option, 1)) from None
        for rate in rates:
            if rate in overrides and overrides[rate] != count:
                raise UserError(f"{option} {spec!r}: rate {rate_label(rate)} is given {overrides[rate]} and {count} "
                                "epochs")
            overrides[rate] = count
    if default is None:
        raise UserError(f"{option} {spec!r}: no default epoch count; start with one, e.g. 10,0.6:0.9:0.1=40")
    return default, tuple(sorted(overrides.items()))


def describe_per_rate(default: int, overrides) -> str:
    """"10 epochs (40 at 60%, 70%)": a per-rate epoch budget, for headers and logs."""
    groups: dict[int, list[float]] = {}
    for rate, count in overrides:
        if count != default:
            groups.setdefault(int(count), []).append(float(rate))
    text = f"{default} epoch" + ("" if default == 1 else "s")
    if groups:
        text += " (" + "; ".join(f"{count} at {', '.join(rate_label(r) for r in sorted(rates))}"
                                 for count, rates in sorted(groups.items())) + ")"
    return text
