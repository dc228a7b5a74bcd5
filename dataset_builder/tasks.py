"""The builder's engines (engine.py) for work of the core's commands: ``apcg generate
--engine dask`` hands its part tasks here through the ``apcg.engines`` entry point
(pyproject.toml), so apcg_core imports nothing above it and there is one engine machinery."""

from __future__ import annotations

import contextlib

from .engine import RunSettings, get_engine


@contextlib.contextmanager
def run_tasks(name: str, workers: int = 1, address: str | None = None, output: str = "",
              connect_timeout_s: float | None = None):
    """The engine called ``name``, checked (a bad address costs nothing) and started: yields
    ``run(fn, tasks)``, the results in completion order, as a dataset build's shards."""
    runner = get_engine(name)
    settings = RunSettings(workers=workers, address=address, output=output,
                           connect_timeout_s=connect_timeout_s)
    runner.check(settings)
    with runner.start(settings) as run:
        yield run
