"""Several files written as one set (``core.common.atomic.write_set``; ``psfspace deblur
--parts``): a writer stopped at any step leaves the old set, or part of the new one,
never files of two runs side by side."""

import os

import numpy as np
import pytest
import tifffile

from napari_psfspace.core.common import atomic

NAMES = ("d.tif", "d.sparse.tif", "d.smooth.tif")


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


DEAD = _dead_pid()


def _write(folder, tag):
    atomic.write_set([(folder / n, lambda fh, t=tag: fh.write(t)) for n in NAMES])


def _state(folder):
    return {n: (folder / n).read_bytes() for n in NAMES if (folder / n).exists()}


@pytest.mark.parametrize("call", ["unlink", "replace"])
def test_a_writer_stopped_at_any_step_leaves_no_mixed_set(tmp_path, monkeypatch, call):
    """Stopped at each removal and each rename in turn (what ``kill -9`` at that moment
    leaves): the files there are all old or all new, the main file (first) present
    only with its whole set; the next write removes the stopped writer's temporary
    files and leaves the new set whole."""
    real = {"unlink": os.unlink, "replace": os.replace}
    for stop in range(len(NAMES)):
        _write(tmp_path, b"old")
        state = {"n": 0, "dead": False}

        def patched(kind, state=state, stop=stop):
            def op(*args, **kw):
                if state["dead"]:  # killed: nothing more runs, no cleaning up
                    raise KeyboardInterrupt
                if kind == call:
                    if state["n"] == stop:
                        state["dead"] = True
                        raise KeyboardInterrupt
                    state["n"] += 1
                return real[kind](*args, **kw)
            return op

        for kind in real:
            monkeypatch.setattr(os, kind, patched(kind))
        with pytest.raises(KeyboardInterrupt):
            _write(tmp_path, b"new")
        for kind, fn in real.items():
            monkeypatch.setattr(os, kind, fn)
        # what a killed writer leaves: its temporary files under a pid that runs no more
        for name in os.listdir(tmp_path):
            if name.endswith(".tmp"):
                os.rename(tmp_path / name,
                          tmp_path / name.replace(f".{os.getpid()}.", f".{DEAD}."))
        state = _state(tmp_path)
        assert len(set(state.values())) <= 1, (call, stop, state)  # never a mix
        if "d.tif" in state:
            assert len(state) == 3  # the main file only with its whole set
        _write(tmp_path, b"new")
        assert _state(tmp_path) == dict.fromkeys(NAMES, b"new")
        assert sorted(os.listdir(tmp_path)) == sorted(NAMES)  # no temporary file left


def test_deblur_parts_are_one_set_naming_each_other(tmp_path):
    import napari_psfspace as ps
    from napari_psfspace.cli import main

    image, truth = ps.simulate_beads((128, 128), 4, seed=1)
    tifffile.imwrite(tmp_path / "sim.tif", image)
    rng = np.random.default_rng(0)
    ps.ProductConvolution(rng.random((2, 9, 9)), 0.1 + rng.random((2, 3, 3)),
                          shape=(128, 128), grid=(np.linspace(0, 127, 3),
                                                  np.linspace(0, 127, 3))).save(
        tmp_path / "m.npz")
    assert main(["deblur", str(tmp_path / "sim.tif"), "--model", str(tmp_path / "m.npz"),
                 "-o", str(tmp_path / "d.tif"), "--parts", "-q", "--max-iter", "5"]) == 0
    import json

    for name in NAMES:
        with tifffile.TiffFile(tmp_path / name) as tif:
            info = json.loads(tif.imagej_metadata["Info"])
        assert info["set"] == list(NAMES)


def test_deblur_parts_killed_at_any_time_leave_one_runs_set(tmp_path):
    """``kill -9`` of ``psfspace deblur --parts`` at times spread over its end (where it
    writes), eight times: the files there always come from one run (their ``set_run``),
    the main file only with its whole set; the next run leaves its set whole and no
    temporary file."""
    import json
    import signal
    import subprocess
    import sys
    import time

    import napari_psfspace as ps

    image, _ = ps.simulate_beads((128, 128), 4, seed=1)
    tifffile.imwrite(tmp_path / "sim.tif", image)
    rng = np.random.default_rng(0)
    ps.ProductConvolution(rng.random((2, 9, 9)), 0.1 + rng.random((2, 3, 3)),
                          shape=(128, 128), grid=(np.linspace(0, 127, 3),) * 2).save(
        tmp_path / "m.npz")
    cmd = [sys.executable, "-m", "napari_psfspace.cli", "deblur", str(tmp_path / "sim.tif"),
           "--model", str(tmp_path / "m.npz"), "-o", str(tmp_path / "d.tif"), "--parts",
           "-q", "--max-iter", "20"]

    def runs():
        found = {}
        for name in NAMES:
            if (tmp_path / name).exists():
                with tifffile.TiffFile(tmp_path / name) as tif:
                    found[name] = json.loads(tif.imagej_metadata["Info"])["set_run"]
        return found

    t0 = time.monotonic()
    subprocess.run(cmd, check=True, capture_output=True)
    whole = time.monotonic() - t0
    for i in range(8):
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(whole * (0.6 + 0.5 * i / 8))  # around the writes, or after the end
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        found = runs()
        assert len(set(found.values())) <= 1, found  # never two runs' files together
        assert "d.tif" not in found or len(found) == 3, found
    subprocess.run(cmd, check=True, capture_output=True)
    assert len(set(runs().values())) == 1 and len(runs()) == 3
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
