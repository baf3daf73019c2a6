"""Pure numpy estimation algorithms for MagStation (no I/O, no server imports); the sequential
loops compiled by numba, whose cache is kept true to the sources here (``kernel_cache``)."""
from estimators.kernel_cache import keep_consistent as _keep_consistent

_keep_consistent()
