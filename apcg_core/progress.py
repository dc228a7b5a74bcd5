"""Progress of long work on stderr: a tqdm bar when tqdm is installed, else a line per update.
One class for every command (dataset build, generate), so they report alike."""

from __future__ import annotations

import sys


class Progress:
    def __init__(self, total: int, unit: str, enabled: bool = True, done: int = 0) -> None:
        self.total, self.done, self.unit, self.enabled = total, done, unit, enabled
        self.bar = None
        if enabled:
            try:
                from tqdm import tqdm
                self.bar = tqdm(total=total, initial=done, unit=unit, unit_scale=True,
                                smoothing=0.1, file=sys.stderr)
            except ImportError:
                self.bar = None

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        elif self.enabled:
            print(f"{self.done:,} / {self.total:,} {self.unit}s "
                  f"({100 * self.done / max(1, self.total):.0f}%)", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def say(line: str) -> None:
    """One line on stderr from any thread, above a progress bar being drawn (tqdm's own
    write, which clears the bar and draws it again under the line)."""
    try:
        from tqdm import tqdm
    except ImportError:
        print(line, file=sys.stderr, flush=True)
    else:
        tqdm.write(line, file=sys.stderr)
