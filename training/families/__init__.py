"""Model families at training time: one module per family (``cgan``, ``apcg_plus``,
``baselines``), each defining the family object registered under the ``apcg.model_families``
entry points (pyproject.toml), on the shared :mod:`.base`. Their runtime is
``apcg_core/families/<family>.py``, their networks ``apcg_core/nn/<family>.py``."""
