"""training: every model family's training, export, evaluation protocol, figures and reports
(see DEVELOPERS.md). Imports torch where a step needs it."""
