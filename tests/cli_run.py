"""Running `apcg` in this process as a user would, and reading its one-line refusal."""

from __future__ import annotations

from apcg_core.cli import main


def run(argv, capsys) -> tuple[int, str, str]:
    """``apcg argv`` through the real main: (exit status, stdout, stderr)."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else 2
    out = capsys.readouterr()
    return rc, out.out, out.err


def one_error(rc: int, err: str, *words: str) -> str:
    """The one error line of a refusal (exit 2, no traceback), holding every one of ``words``."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "error:" in lines[0], err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]
