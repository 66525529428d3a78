"""Deblurring a stack file into an OME-Zarr tile by tile, resumable
(``napari_psfspace.deblur_store`` and ``psfspace deblur3d --memory/--tile/--resume``)."""

import numpy as np
import pytest
import tifffile

from napari_psfspace.cli import main
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.deblur_store import iter_deblur_to_store, work_folder
from napari_psfspace.io import read_stack
from test_volume_blocks import _operator

pytest.importorskip("zarr", minversion="3", reason="the OME-Zarr writer takes zarr 3")


@pytest.fixture
def files(tmp_path):
    op = _operator(seed=5, shape=(6, 90, 80))
    rng = np.random.default_rng(3)
    stack = rng.poisson(op.apply((rng.random(op.image_shape) < 0.01) * 300.0) + 5)
    stack = stack.astype(np.uint16)
    tifffile.imwrite(tmp_path / "in.tif", stack, imagej=True,
                     resolution=(1 / 0.1, 1 / 0.1), metadata={"spacing": 0.3, "unit": "um"})
    op.save(tmp_path / "m3.npz")
    return tmp_path, op, stack


def _cli(d, *extra):
    return main(["deblur3d", str(d / "in.tif"), "--model", str(d / "m3.npz"), "-q",
                 "--iterations", "5", *extra])


def test_a_tiff_becomes_an_ome_zarr_equal_to_the_whole_volumes_result(files):
    d, op, stack = files
    assert _cli(d, "-o", str(d / "out.zarr"), "--tile", "32") == 0
    got, info = read_stack(d / "out.zarr")
    assert info.pixel_size == pytest.approx(0.1) and info.z_spacing == pytest.approx(0.3)
    whole = richardson_lucy_3d(stack, op, n_iter=5).volume
    assert got.dtype == np.float32 and np.abs(got - whole).max() <= 1e-4 * whole.max()
    assert not (d / "out.zarr.iterates").exists()
    # an OME-Zarr input, tiles from a memory budget
    assert main(["deblur3d", str(d / "out.zarr"), "--model", str(d / "m3.npz"), "-q",
                 "--iterations", "1", "-o", str(d / "again.zarr"), "--memory", "1GB"]) == 0
    assert read_stack(d / "again.zarr")[0].shape == stack.shape


def test_an_interrupted_run_resumes_to_the_same_result(files, capsys):
    d, op, _ = files
    assert _cli(d, "-o", str(d / "ref.zarr"), "--tile", "32") == 0
    ref = read_stack(d / "ref.zarr")[0]
    out = d / "out.zarr"
    gen = iter_deblur_to_store(d / "in.tif", op, out, n_iter=5, tile=32)
    for p in gen:  # stopped after the third iteration, as a kill would leave it
        if p.stage == "iteration" and p.fraction >= 0.6:
            break
    gen.close()
    # the output is made at the start and holds no chunk until the last iteration
    from napari_psfspace.ome_zarr import missing_chunks, open_ome_zarr_output

    assert (d / "out.zarr.iterates" / "state.json").exists()
    assert len(missing_chunks(open_ome_zarr_output(out), out)) == 54  # 6 planes of 3 x 3
    capsys.readouterr()
    assert _cli(d, "-o", str(out), "--tile", "32") == 2  # not silently overwritten
    assert "--resume" in capsys.readouterr().err
    assert _cli(d, "-o", str(out), "--tile", "32", "--resume") == 0
    assert np.abs(read_stack(out)[0] - ref).max() <= 1e-6 * ref.max()
    assert not (d / "out.zarr.iterates").exists()
    assert _cli(d, "-o", str(out), "--tile", "32", "--resume") == 2
    assert "it is complete" in capsys.readouterr().err


def test_a_resumed_run_writes_only_the_missing_chunks(files):
    """The last iteration writes the output's chunks as it makes them. A run stopped
    after it, before the work folder is removed, whose output then lost a chunk (here
    plane 0 is marked 7 to see that the chunks there are kept, and a chunk's temporary
    file is left as a killed writer leaves it): the resumed run iterates no more,
    removes the temporary file and writes the missing chunk alone."""
    import os

    from napari_psfspace.ome_zarr import open_ome_zarr_output

    d, op, _ = files
    for _ in iter_deblur_to_store(d / "in.tif", op, d / "full.zarr", n_iter=5, tile=32):
        pass
    full = read_stack(d / "full.zarr")[0]
    out = d / "b.zarr"
    gen = iter_deblur_to_store(d / "in.tif", op, out, n_iter=5, tile=32)
    for p in gen:
        if p.stage == "write":
            break
    gen.close()
    assert os.path.isdir(work_folder(out))
    assert np.array_equal(read_stack(out)[0], full)  # the last iteration wrote it
    open_ome_zarr_output(out)[0] = 7.0
    os.remove(out / "0" / "2" / "1" / "1")
    torn = out / "0" / "1" / "0" / "0.abc.partial"
    torn.write_bytes(b"torn")
    assert _cli(d, "-o", str(out), "--tile", "32", "--resume") == 0
    got = read_stack(out)[0]
    assert np.all(got[0] == 7.0) and np.array_equal(got[1:], full[1:])
    assert not torn.exists() and not os.path.isdir(work_folder(out))


def _stopped_before_writing(d, op, out):
    """A run stopped once its iterations are done, before the output is written."""
    gen = iter_deblur_to_store(d / "in.tif", op, out, n_iter=2, tile=32)
    for p in gen:
        if p.stage == "write":
            break
    gen.close()


def _snapshot(folder):
    import os

    return {os.path.relpath(os.path.join(f, n), folder): open(os.path.join(f, n), "rb").read()
            for f, _, names in os.walk(folder) for n in names}


@pytest.mark.parametrize("damage, says", [
    ("chunks", "chunks are (1, 16, 16), not (1, 32, 32)"),
    ("dtype", "it holds float64"),
    ("readonly", "is not writable"),
])
def test_a_resume_into_a_store_it_cannot_finish_is_refused_with_nothing_lost(
        files, capsys, damage, says):
    import os
    import stat

    from napari_psfspace.ome_zarr import create_ome_zarr

    d, op, stack = files
    out = d / "out.zarr"
    _stopped_before_writing(d, op, out)
    import shutil

    shutil.rmtree(out)  # an output that is not this run's in its place
    arr = create_ome_zarr(out, stack.shape, chunk=16 if damage == "chunks" else 32,
                          dtype="float64" if damage == "dtype" else "float32")
    arr[0] = 7.0
    if damage == "readonly":
        for folder, _, names in os.walk(out):
            for n in names:
                os.chmod(os.path.join(folder, n), stat.S_IRUSR)
    before = _snapshot(d)
    capsys.readouterr()
    assert _cli(d, "-o", str(out), "--tile", "32", "--iterations", "2", "--resume") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert _snapshot(d) == before  # the iterates and the chunks written are kept


@pytest.mark.parametrize("damage, says", [
    # 6 planes of 3 x 3 chunks of 32 px (90 x 80 px)
    ("missing", "is incomplete: 1 of its 54 chunks are missing"),
    ("complex", "holds complex64 data"),
])
def test_a_damaged_ome_zarr_input_is_refused_before_any_work(files, capsys, damage, says):
    import os

    from napari_psfspace.ome_zarr import create_ome_zarr

    d, op, stack = files
    arr = create_ome_zarr(d / "in.zarr", stack.shape, chunk=32, voxel_size=(0.3, 0.1, 0.1),
                          dtype="complex64" if damage == "complex" else "uint16")
    arr[:] = stack
    if damage == "missing":
        os.remove(d / "in.zarr" / "0" / "3" / "1" / "2")
    capsys.readouterr()
    for extra in (["--tile", "32"], []):
        out = d / ("o.zarr" if extra else "o.tif")
        assert main(["deblur3d", str(d / "in.zarr"), "--model", str(d / "m3.npz"), "-q",
                     "-o", str(out), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and says in err, err
        assert not out.exists() and not (d / "o.zarr.iterates").exists()


def test_a_disk_too_small_for_the_iterates_is_refused_before_any_work(files, capsys,
                                                                      monkeypatch):
    import shutil
    from collections import namedtuple

    from napari_psfspace import deblur_store

    d, _, stack = files
    usage = namedtuple("usage", "total used free")
    need = deblur_store.DISK_VOLUMES * 4 * stack.size
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(need, 0, need - 1))
    capsys.readouterr()
    assert _cli(d, "-o", str(d / "out.zarr"), "--tile", "32") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "6 float32 volumes" in err, err
    assert not (d / "out.zarr").exists() and not (d / "out.zarr.iterates").exists()
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(need, 0, need))
    assert _cli(d, "-o", str(d / "out.zarr"), "--tile", "32") == 0


def test_the_stack_is_sampled_once(files, monkeypatch):
    """The background and start, read from the stack before any work (its refusals),
    are passed on: the tiles do not read the stack's sample again (a lazy file's whole
    read, on a large stack)."""
    from napari_psfspace.core.volume import exchange3d

    d, op, _ = files
    calls = []
    real = exchange3d.stack_statistics
    monkeypatch.setattr(exchange3d, "stack_statistics",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    from napari_psfspace.deblur_store import deblur_to_store

    run = deblur_to_store(d / "in.tif", op, d / "once.zarr", n_iter=2, tile=32)
    assert calls == [] and run.background is not None
