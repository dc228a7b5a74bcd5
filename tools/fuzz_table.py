"""The fuzz suite's tally as a markdown table (docs/ERRORS.md).

    APCG_FUZZ_REPORT=/tmp/fuzz.json HYPOTHESIS_PROFILE=ci \
        .venv/bin/python -m pytest -q tests/test_fuzz.py
    .venv/bin/python tools/fuzz_table.py /tmp/fuzz.json

Only cases that passed are tallied: a traceback, a silently wrong result or a user's file
changed fails the suite instead, so those columns are 0 whenever the suite is green.
"""

from __future__ import annotations

import json
import sys
from collections import Counter, defaultdict

OUTCOMES = ("clear error", "handled")


def table(cases: list[dict]) -> str:
    by_class: dict = defaultdict(Counter)
    for c in cases:
        by_class[c["class"]][c["outcome"]] += 1
    rows = ["| class | tried | clear error | handled | traceback | silently wrong | data lost |",
            "|---|---|---|---|---|---|---|"]
    total: Counter = Counter()
    for name in sorted(by_class):
        n = by_class[name]
        total.update(n)
        rows.append(f"| {name} | {sum(n.values())} | {n['clear error']} | {n['handled']} "
                    "| 0 | 0 | 0 |")
    rows.append(f"| **all** | **{sum(total.values())}** | **{total['clear error']}** | "
                f"**{total['handled']}** | **0** | **0** | **0** |")
    unknown = set(total) - set(OUTCOMES)
    if unknown:
        raise SystemExit(f"unexpected outcomes in the tally: {sorted(unknown)}")
    return "\n".join(rows)


if __name__ == "__main__":
    print(table(json.loads(open(sys.argv[1]).read())))
