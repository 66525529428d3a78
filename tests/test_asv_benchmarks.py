"""The asv benchmarks (``benchmarks/benchmarks.py``) run: each class's setup and every
``time_``/``peakmem_`` method, at sizes small enough for the suite (the classes' sizes
are their attributes). A benchmark that breaks with the code fails here, not months
later in ``asv run``."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMALL = {
    "EstimateOperator": {"shape": (384, 384), "n_beads": 30},
    "ApplyOperator": {"shape": (96, 96), "n_psf": 3, "psf": 11},
    "RichardsonLucy3D": {"shape": (8, 48, 48), "kernel": (5, 7, 7), "n_iter": 2},
    "Deblur": {"shape": (96, 96), "n_psf": 3, "psf": 11, "max_iter": 3},
}


def _module():
    spec = importlib.util.spec_from_file_location("asv_benchmarks",
                                                  ROOT / "benchmarks" / "benchmarks.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name", sorted(SMALL))
def test_every_benchmark_runs(name):
    cls = getattr(_module(), name)
    bench = cls()
    for attr, value in SMALL[name].items():
        assert hasattr(cls, attr), (name, attr)
        setattr(bench, attr, value)
    bench.setup()
    timed = [m for m in dir(cls) if m.startswith(("time_", "peakmem_"))]
    assert timed, name
    for method in timed:
        getattr(bench, method)()


def test_every_benchmark_class_is_exercised():
    mod = _module()
    classes = {n for n, v in vars(mod).items()
               if isinstance(v, type) and any(m.startswith(("time_", "peakmem_")) for m in dir(v))}
    assert classes == set(SMALL)
