"""BLAS runs on one thread while the package's estimates run, and gets its threads back
after (core/common/threads.py: the estimates' many small SVDs and eigendecompositions
were 2x slower with OpenBLAS's own threads on 2 cores; bench/RESULTS.md)."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from napari_psfspace.core.common.threads import blas_threads


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():
    np.linalg.svd(np.ones((3, 3)))  # numpy's BLAS loaded
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl can control is loaded")
    with threadpool_limits(limits=2, user_api="blas"):
        yield


def test_a_function_and_a_generator_run_on_one_blas_thread(two_blas_threads,
                                                           monkeypatch):
    monkeypatch.delenv("PSFSPACE_BLAS_THREADS", raising=False)

    @blas_threads
    def function():
        return _blas_threads()

    @blas_threads
    def generator():
        yield _blas_threads()
        return "done"

    assert set(function()) == {1}
    assert set(_blas_threads()) == {2}
    gen = generator()
    assert set(next(gen)) == {1}
    assert set(_blas_threads()) == {1}  # held while the generator is suspended
    with pytest.raises(StopIteration) as stop:
        next(gen)
    assert stop.value.value == "done"
    assert set(_blas_threads()) == {2}
    # an error inside gives the threads back too
    @blas_threads
    def failing():
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        failing()
    assert set(_blas_threads()) == {2}


def test_the_environment_chooses_the_limit(two_blas_threads, monkeypatch):
    @blas_threads
    def function():
        return _blas_threads()

    monkeypatch.setenv("PSFSPACE_BLAS_THREADS", "0")  # leave BLAS as it is
    assert set(function()) == {2}
    monkeypatch.setenv("PSFSPACE_BLAS_THREADS", "1")
    assert set(function()) == {1}
    monkeypatch.setenv("PSFSPACE_BLAS_THREADS", "many")
    with pytest.raises(ValueError, match="PSFSPACE_BLAS_THREADS.*'many'"):
        function()


def test_an_estimate_runs_on_one_blas_thread_and_gives_them_back(two_blas_threads,
                                                                  monkeypatch):
    from napari_psfspace.core.model.estimate import iter_estimate
    from napari_psfspace.core.simulation import simulate_beads

    monkeypatch.delenv("PSFSPACE_BLAS_THREADS", raising=False)
    image, truth = simulate_beads((256, 256), 12, seed=2)
    gen = iter_estimate(image, psf_radius=float(truth.psf_radius))
    next(gen)  # the first progress record: the estimate has started
    assert set(_blas_threads()) == {1}
    for _ in gen:
        pass
    assert set(_blas_threads()) == {2}


@pytest.mark.parametrize("module, name", [
    ("napari_psfspace.core.model.estimate", "iter_estimate"),
    ("napari_psfspace.core.family.estimate", "iter_estimate_family"),
    ("napari_psfspace.core.restore.identify", "identify_operator"),
    ("napari_psfspace.core.volume.estimate3d", "iter_estimate_operator_3d"),
    ("napari_psfspace.core.diagnosis.loop", "iter_diagnose"),
    ("napari_psfspace.core.diagnosis.crossfit", "iter_crossfit"),
    ("napari_psfspace.core.model.review", "iter_patch_review"),
])
def test_every_estimate_s_entry_point_limits_blas(module, name):
    import importlib
    import inspect

    fn = getattr(importlib.import_module(module), name)
    assert getattr(fn, "__wrapped__", None) is not None, name
    # the wrapper keeps the signature the widgets and docs read
    assert inspect.signature(fn) == inspect.signature(fn.__wrapped__)
