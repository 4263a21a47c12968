"""Tools around the pipeline, run from the repository root (`python -m tools.<name>`)."""
