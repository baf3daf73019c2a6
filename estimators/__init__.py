"""Pure numpy estimation algorithms for MagStation (no I/O, no server imports)."""
