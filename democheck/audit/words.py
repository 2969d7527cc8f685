"""How numbers read in a reason: rounded for a person, never so far that two numbers compared read the same."""

from __future__ import annotations

MAX_DIGITS = 8


def pair(value: float, reference: float, digits: int = 2) -> tuple[str, str]:
    """``value`` and the ``reference`` it is compared with, each to ``digits`` significant figures, or to as many
    more (at most ``MAX_DIGITS``) as tell them apart: '0.99998' against '0.99999', not '1' against '1'.  Either
    one that is float noise beside the other (under 10^-MAX_DIGITS of it: the sine of an angle of 0) reads 0."""
    scale = max(abs(value), abs(reference))
    value, reference = (0.0 if abs(x) < 10.0 ** -MAX_DIGITS * scale else x for x in (value, reference))
    for d in range(digits, MAX_DIGITS + 1):
        a, b = f"{value:.{d}g}", f"{reference:.{d}g}"
        if a != b or value == reference:
            return a, b
    return a, b


def percent(share: float) -> str:
    """A share as a percentage, two significant figures under 10% so that a small share that counted does not
    read as none: '35%', '0.85%', '0.012%', '0%'."""
    p = 100 * float(share)
    return "0%" if p == 0 else "under 0.01%" if p < 0.01 else f"{p:.0f}%" if p >= 10 else f"{p:.2g}%"


def factor(times: float) -> str:
    """How many times, as a person reads it: two significant figures under 10 ('0.5', '7.4'), whole from there
    ('56', '190', not '1.9e+02')."""
    return f"{times:.2g}" if abs(times) < 10 else f"{times:.0f}"
