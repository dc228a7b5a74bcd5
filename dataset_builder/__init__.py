"""dataset_builder (filled in by later issues)."""
