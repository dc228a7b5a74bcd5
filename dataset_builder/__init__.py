"""dataset_builder: the exact simulator's backends (embree, Blender, the point z-buffer), the
dataset planner and writer, and their command line (docs/DATASET.md)."""
