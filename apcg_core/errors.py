"""Error types shared by the whole project.

Every error names the offending value and what would have been accepted, so that a user who
passes a bad condition, file or cloud learns how to fix it from the message alone.
"""


class APCGError(Exception):
    """Base class of the project's own errors."""


class InputError(APCGError, ValueError):
    """A value given by the caller is not acceptable (out of range, NaN, wrong shape...)."""


def check_finite(name: str, value: float) -> float:
    """Return ``value`` as a float, or raise naming ``name`` when it is NaN or infinite, or
    not a number: a text ("5000", which float() would read) or a bool (True as 1) is refused,
    as every option and file value is checked as the number it is."""
    if isinstance(value, (str, bytes, bool)) or getattr(
            getattr(value, "dtype", None), "kind", "") == "b":  # numpy's bools too
        raise InputError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number, got {value!r}") from exc
    if v != v or v in (float("inf"), float("-inf")):
        raise InputError(f"{name} must be finite, got {value!r}")
    return v


def check_int(name: str, value, lo: int, hi: int | None = None, hint: str = "") -> int:
    """Return ``value`` as an int if it is a whole number (not a bool) in ``lo``..``hi``
    (no upper bound when ``hi`` is None), else raise naming ``name`` and what is accepted."""
    from numbers import Integral
    ok = isinstance(value, Integral) and not isinstance(value, bool) and value >= lo and (
        hi is None or value <= hi)
    if not ok:
        accepted = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise InputError(f"{name} must be an integer {accepted}{hint}, got {value!r}")
    return int(value)


def distinct(value: float, bound: float) -> str:
    """``value`` with the fewest significant digits (6 at least) that tell it from ``bound``
    as that is shown (6 digits): 18000.000001 against 18000, not 18000 against 18000."""
    shown = f"{bound:.6g}"
    for digits in range(6, 18):
        text = f"{value:.{digits}g}"
        if text != shown and float(text) != float(shown):
            return text
    return repr(float(value))


def check_range(name: str, value: float, lo: float, hi: float, unit: str = "",
                scale: float = 1.0, open_ends: bool = False) -> float:
    """Return ``value`` if ``lo <= value <= hi`` (strict when ``open_ends``), else raise.

    ``scale`` converts the internal unit to the one shown in the message (e.g. rad -> deg),
    so the message speaks the user's units.
    """
    v = check_finite(name, value)
    inside = (lo < v < hi) if open_ends else (lo <= v <= hi)
    if not inside:
        br = ("(", ")") if open_ends else ("[", "]")
        raise InputError(
            f"{name} = {distinct(v * scale, (lo if v < lo else hi) * scale)}{unit} is out "
            "of range; accepted: "
            f"{br[0]}{lo * scale:.6g}{unit}, {hi * scale:.6g}{unit}{br[1]}"
        )
    return v


def os_error_message(exc: OSError) -> str:
    """A file-system failure as one line: the file (its final name, not the temporary one
    being written), what the system said, and what to do for the usual cases."""
    import errno
    import re

    name = re.sub(r"\.part(\.\w+|\.\d+)*$", "", str(exc.filename)) if exc.filename else None
    what = exc.strerror or str(exc)
    hint = {errno.ENOSPC: "free some space and run the same command again: finished work is "
                          "kept and nothing half-written is left under a final name",
            errno.EDQUOT: "free some space (over the disk quota) and run the same command again",
            errno.EACCES: "check the permissions of the file and its directory",
            errno.EROFS: "the file system is read-only; write somewhere else"}.get(exc.errno)
    return ": ".join(filter(None, [f"cannot write or read {name}" if name else None, what, hint]))
