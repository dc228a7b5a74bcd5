"""Named points where a test can hold a command, to interrupt it at a known moment.

A test that sends Ctrl-C, SIGTERM or SIGKILL to a command must not race it: on a loaded machine
the command may finish before the signal, or not have started what the test means to
interrupt. Instead the test names a point here and the command waits there:

    APCG_TEST_WAIT_AT=build.shard-written   (several: comma-separated)
    APCG_TEST_WAIT_DIR=/some/empty/dir

A process passing a named point writes ``DIR/NAME.reached`` (its pid) and waits until
``DIR/NAME.go`` exists; from then on it passes that point freely. The test waits for the
reached file, sends its signal, and creates the go file (a signal that raises in the waiting
process ends the wait at once). Nothing waits for ever: after ``APCG_TEST_WAIT_S`` seconds
(default 300) without a go file the wait fails. Without ``APCG_TEST_WAIT_AT`` a point costs one
dictionary lookup. ``tests/conftest.py``'s ``hold`` fixture drives it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

ENV_AT = "APCG_TEST_WAIT_AT"
ENV_DIR = "APCG_TEST_WAIT_DIR"
ENV_SECONDS = "APCG_TEST_WAIT_S"

# Every point, where it is, and what holds there. A point not listed here is refused, so a
# test cannot wait for a point that no code passes.
POINTS = {
    "build.workers-starting": "dataset build, in the build's own process: the local pool or "
                              "the local Dask cluster has been started, its workers are "
                              "booting, Ctrl-C is blocked until the point is passed",
    "build.shard-computing": "dataset build, wherever a shard is computed: a shard task has "
                             "started (a cluster's scheduler sees it executing), nothing "
                             "written yet",
    "build.shard-written": "dataset build, wherever a shard is computed (this process, a pool "
                           "or cluster worker): a shard's file has just been written whole",
    "scene.frame-computed": "scene sequence, wherever a frame is computed: a frame's cloud "
                            "is made, its file not yet written",
    "generate.block-written": "generate: a block of clouds has just been written to the "
                              "output's temporary file",
    "generate.part-written": "generate, a resumable request: a part file of its clouds has "
                             "just been written whole into OUT.parts/",
    "distill.checkpoint-written": "apcg distill: a checkpoint of the run has just been written "
                                  "whole (RUN/checkpoint.pt)",
    "output.held": "any command (apcg_core.outputs): its first output file is written whole "
                   "under its temporary name and held; nothing is under a final name yet",
    "output.committing": "any command: its held outputs are being renamed to their final "
                         "names, Ctrl-C and SIGTERM held until they all are",
    "cli.command-ended": "any apcg command, in its own process: the command has ended and its "
                         "exit status is decided, the interpreter not yet gone; Ctrl-C and "
                         "SIGTERM are held back from here on",
}


def wait_point(name: str) -> None:
    """Hold here when a test asked for point ``name`` (see the module's docstring)."""
    wanted = os.environ.get(ENV_AT)
    if not wanted:
        return
    if name not in POINTS:
        raise ValueError(f"unknown test point {name!r}; known: {', '.join(POINTS)}")
    if name not in (w.strip() for w in wanted.split(",")):
        return
    directory = Path(os.environ[ENV_DIR])
    go = directory / f"{name}.go"
    if go.exists():
        return
    reached = directory / f"{name}.reached"
    tmp = directory / f".{name}.{os.getpid()}.tmp"
    tmp.write_text(f"{os.getpid()}\n")
    os.replace(tmp, reached)  # the test never reads a half-written pid
    seconds = float(os.environ.get(ENV_SECONDS, "300"))
    deadline = time.monotonic() + seconds
    while not go.exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"test point {name}: no {go} within {seconds:g} s")
        time.sleep(0.005)
