"""The torch networks of each model family, one module per family (``cgan``, ``apcg_plus``,
``baselines``): what training fits and what a torch runtime runs. Importing a module of this
package imports torch; the rest of apcg_core never needs it."""
