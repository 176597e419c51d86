"""float64 values as the shortest decimal text that reads back to the same bits, in the
layout Arrow's CSV writer gives them, without importing pyarrow (and, through it, pandas):
0.2-0.3 s of a small command's start.

The digits are Python's ``repr`` (the shortest that round-trips). The layout is Arrow's:
fixed notation when the decimal exponent e of the leading digit is in -6 <= e < 10
(``0.000001``, ``123456789``, no ``.0`` on a whole number), else ``d.ddde+X``/``d.ddde-X``
with the exponent unpadded; ``0``, ``-0``, ``nan``, ``inf``, ``-inf``.
"""

from __future__ import annotations

import numpy as np

#: Fixed notation for a leading-digit exponent in [LOW, HIGH).
LOW, HIGH = -6, 10


def float_texts(values: np.ndarray) -> list[str]:
    """Each value of a float64 array as text (see the module's layout)."""
    texts = list(map(repr, values.tolist()))
    with np.errstate(invalid="ignore"):
        a = np.abs(values)
        whole = values == np.trunc(values)
        # repr's layout already is Arrow's for these: fixed, not whole, 1e-4 <= |v| < 1e10
        same = (a >= 1e-4) & (a < 1e10) & ~whole
        # a whole number below 1e10: repr's "N.0" less its ".0" (0 and -0 too)
        point = whole & (a < 1e10)
        # below 1e-6: repr's "d.ddde-XX", the exponent unpadded
        small = (a > 0) & (a < 1e-6)
        # from 1e-6 to 1e-4: repr's "d.ddde-0X" in fixed notation
        tenths = (a >= 1e-6) & (a < 1e-4)
    for i in np.flatnonzero(point).tolist():
        texts[i] = texts[i][:-2]
    for i in np.flatnonzero(small).tolist():
        texts[i] = texts[i].replace("e-0", "e-")
    for i in np.flatnonzero(tenths).tolist():
        mantissa, _, exp = texts[i].partition("e")
        sign = "-" if mantissa[0] == "-" else ""
        texts[i] = sign + "0." + "0" * (-int(exp) - 1) + mantissa.lstrip("-").replace(".", "")
    for i in np.flatnonzero(~(same | point | small | tenths)).tolist():
        texts[i] = _layout(texts[i])
    return texts


def _layout(text: str) -> str:
    """One value's ``repr`` in Arrow's layout."""
    if text in ("nan", "inf", "-inf"):
        return text
    sign = "-" if text.startswith("-") else ""
    body = text.lstrip("-")
    mantissa, _, exp = body.partition("e")
    whole, _, frac = mantissa.partition(".")
    shift = int(exp) if exp else 0
    digits = whole + frac
    stripped = digits.lstrip("0")
    if not stripped.rstrip("0"):  # zero
        return sign + "0"
    # the decimal exponent of the leading digit
    e = len(whole) - (len(digits) - len(stripped)) - 1 + shift
    digits = stripped.rstrip("0")
    if LOW <= e < HIGH:
        if e >= 0:
            out = (digits + "0" * (e + 1 - len(digits)) if len(digits) <= e + 1
                   else digits[:e + 1] + "." + digits[e + 1:])
        else:
            out = "0." + "0" * (-e - 1) + digits
    else:
        out = digits[0] + ("." + digits[1:] if len(digits) > 1 else "") + \
            ("e+" if e >= 0 else "e-") + str(abs(e))
    return sign + out

