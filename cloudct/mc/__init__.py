"""The Monte Carlo engine: grid traversal, sun source, local estimation, backward tracing."""
