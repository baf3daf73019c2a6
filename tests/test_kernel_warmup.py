"""The warm-up run by ./run and ./test reaches every numba kernel of the estimators, so none is
compiled later inside the station's replay (a stall of seconds) or by each test worker."""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import re

from numba.core.registry import CPUDispatcher

import estimators
from estimators.kernel_warmup import warm_up


def _kernels() -> tuple[dict[str, CPUDispatcher], dict[str, set]]:
    """The estimators' kernels by qualified name, and the names each is bound to in any module."""
    found, names = {}, {}
    for info in pkgutil.iter_modules(estimators.__path__):
        module = importlib.import_module(f"estimators.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and getattr(value.py_func, "__module__", "").startswith("estimators"):
                key = f"{value.py_func.__module__}.{value.py_func.__name__}"
                found[key] = value
                names.setdefault(key, {value.py_func.__name__}).add(name)
    return found, names


def test_the_warm_up_compiles_every_estimator_kernel():
    """Every kernel is called by the warm-up or from inside another kernel (compiled with it: a
    kernel loaded from the cache does not list the ones it calls)."""
    kernels, names = _kernels()
    assert len(kernels) >= 10, sorted(kernels)       # the AHRS supervisor's and the field test's
    called_inside = set()
    for k in kernels.values():
        body = inspect.getsource(k.py_func).split(":", 1)[1]
        called_inside |= set(re.findall(r"\b(\w+)\(", body))
    warm_up()
    cold = sorted(key for key, k in kernels.items() if not k.signatures and not names[key] & called_inside)
    assert not cold, f"kernels the warm-up does not reach: {cold}"
