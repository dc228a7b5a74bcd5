"""Code run in a fresh Python process (a process's compiled kernels, its imports and its
collector start from nothing there): what it printed."""

import os
import subprocess
import sys


def printed(code: str, **env: str) -> str:
    """stdout of ``code`` run by this Python in a new process, with ``env`` added to this
    process's environment (it must exit 0)."""
    return subprocess.run([sys.executable, "-c", code], env={**os.environ, **env},
                          capture_output=True, text=True, check=True).stdout
