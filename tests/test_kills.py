"""``kill -9`` at every write of every command that writes: no torn file, no mixed set,
no stale temporary file after the next run.

Each command runs as a real process under a wrapper that counts its write steps (each
``os.fsync`` that ends a file's writing, each ``os.replace`` or ``os.rename`` that puts
one in place, each ``os.unlink`` of an output) and sends itself ``SIGKILL`` just before
step ``k``. For every ``k`` in turn, into one folder, the run alternates between two
variants of the command (other inputs or settings: other contents), so that a set holding
files of both is seen. After each kill:

* every output there is whole: it reads back, and equals one variant's reference;
* the files of a set all come from one variant, and its main file is there only when
  the whole set is;

and after the kills, a complete run leaves no temporary file in the folder and its set
whole.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import tifffile

import napari_psfspace as ps
from napari_psfspace.cli import main

KILLER = r"""
import os, signal, sys
kill_at = int(os.environ["KILL_AT"])
steps = [0]

def step(real, counted=lambda *a: True):
    def call(*args, **kwargs):
        if counted(*args):
            if steps[0] == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            steps[0] += 1
        return real(*args, **kwargs)
    return call

# a temporary file's removal (a dead writer's, or its own on failure) is not an output's
output = lambda path, *a: not os.fspath(path).endswith(".tmp")
os.fsync, os.replace, os.rename = step(os.fsync), step(os.replace), step(os.rename)
os.unlink = os.remove = step(os.unlink, output)
from napari_psfspace.cli import main
rc = main(sys.argv[1:])
with open(os.environ["KILL_STEPS"], "w") as fh:
    fh.write(str(steps[0]))
sys.exit(rc)
"""

#: command (with {i} the inputs' folder, {o} the outputs', {v} the variant, a or b, and
#: {n} and {ab} its number and aberrations),
#: its outputs (a set: the main file first; one file or a folder alone otherwise)
COMMANDS = {
    "estimate": ("estimate {i}/beads_{v}.tif -o {o}/m.npz --psf-radius 5", ["m.npz"]),
    "simulate": ("simulate -o {o}/s.tif --shape 192 192 --beads 4 --seed {n} "
                 "--aberrations {ab} --truth-grid {o}/t.tif", ["s.tif", "t.tif"]),
    "apply": ("apply {i}/model.npz {i}/beads_{v}.tif -o {o}/a.tif", ["a.tif"]),
    "deblur-parts": ("deblur {i}/beads_{v}.tif --model {i}/model.npz -o {o}/d.tif "
                       "--parts -q --max-iter 5", ["d.tif", "d.sparse.tif", "d.smooth.tif"]),
    "psf": ("psf {i}/model.npz --at 60 {n}0 -o {o}/p.tif", ["p.tif"]),
    "diagnose": ("diagnose {i}/beads_{v}.tif --report {o}/r --psf-radius 5 -q",
                 ["r/report.md", "r/report.json", "r/residual_map_before.png",
                  "r/residual_map_after.png", "r/mean_residual_before.png",
                  "r/mean_residual_after.png", "r/residual_patches_before.png",
                  "r/residual_patches_after.png"]),
    "deblur3d": ("deblur3d {i}/stack_{v}.tif --model {i}/model3d.npz -o {o}/x3.tif "
                 "--iterations 2 -q", ["x3.tif"]),
    "learn": ("learn {i}/focus_{v}.tif -o {o}/f.npz -q", ["f.npz"]),
    "qc": ("qc {i}/focus_{v}.tif -o {o}/q -q", ["q/qc.html", "q/qc_beads.csv", "q/qc.json"]),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("kill_inputs")
    (d / "killer.py").write_text(KILLER)
    for v, seed in (("a", 3), ("b", 4)):
        tifffile.imwrite(d / f"beads_{v}.tif", ps.simulate_beads((192, 192), 16, seed=seed)[0])
    rng = np.random.default_rng(0)
    ps.ProductConvolution(rng.random((2, 9, 9)), 0.1 + rng.random((2, 3, 3)),
                          shape=(192, 192), grid=(np.linspace(0, 191, 3),) * 2).save(
        d / "model.npz")
    op3 = ps.ProductConvolution3D(rng.random((1, 3, 7, 7)), np.ones((1, 2, 2)),
                                  shape=(4, 64, 64), plane=1,
                                  grid=(np.array([0.0, 63]), np.array([0.0, 63])))
    op3.save(d / "model3d.npz")
    for v, seed in (("a", 1), ("b", 2)):
        stack = np.random.default_rng(seed).poisson(50, op3.image_shape).astype(np.float32)
        tifffile.imwrite(d / f"stack_{v}.tif", stack, imagej=True)
        assert main(["simulate", "--focus-series", "7", "-o", str(d / f"focus_{v}.tif"),
                     "--shape", "256", "256", "--beads", "8", "--seed", str(seed)]) == 0
    return d


def _run(inputs, command: str, out, variant: str, kill_at: int = -1) -> tuple[int, int]:
    """Run ``command``'s ``variant`` writing into ``out``: (exit status, write steps)."""
    argv = COMMANDS[command][0].format(
        i=inputs, o=out, v=variant, n=1 if variant == "a" else 2,
        ab="moderate" if variant == "a" else "strong").split()
    env = {**os.environ, "KILL_AT": str(kill_at), "KILL_STEPS": str(out / ".steps")}
    proc = subprocess.run([sys.executable, str(inputs / "killer.py"), *argv], env=env,
                          capture_output=True, text=True)
    steps = int((out / ".steps").read_text()) if proc.returncode == 0 else -1
    (out / ".steps").unlink(missing_ok=True)
    return proc.returncode, steps


def _signature(path) -> str:
    """What a file holds, read back through its format (a torn file fails to read):
    a TIFF's pixels and the input its ImageJ Info names, an archive's arrays, a
    PNG's pixels; for a text (whose JSON and Markdown carry the run's seconds), the
    variant's input it names."""
    name = str(path)
    if name.endswith(".tif"):  # its pixels and the input it names (its Info's source)
        with tifffile.TiffFile(path) as tif:
            pixels = tif.asarray().tobytes()
            source = json.loads((tif.imagej_metadata or {}).get("Info", "{}")).get("source")
        return hashlib.sha1(pixels + str(source).encode()).hexdigest()
    if name.endswith(".npz"):
        with np.load(path, allow_pickle=False) as data:
            return hashlib.sha1(b"".join(data[k].tobytes() for k in sorted(data.files)
                                         if k != "header")).hexdigest()
    if name.endswith(".png"):
        import imageio.v3 as iio

        return hashlib.sha1(iio.imread(path).tobytes()).hexdigest()
    text = path.read_text(encoding="utf-8")
    if name.endswith(".json"):
        json.loads(text)
    for v in "ab":
        if f"beads_{v}.tif" in text or f"focus_{v}.tif" in text:
            return v
    return text


def _variant(out, outputs, refs) -> set[str]:
    """The variants the present files of the set can come from (empty: a file that is
    neither's, or files of different variants together)."""
    can = {"a", "b"}
    for name in outputs:
        if (out / name).exists():
            sig = _signature(out / name)
            can &= {v for v in "ab" if refs[v][name] == sig}
    return can


def _temporaries(folder) -> list[str]:
    return [os.path.join(r, f) for r, _, files in os.walk(folder) for f in files
            if f.endswith(".tmp")]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_command_killed_at_every_write_leaves_whole_files_and_sets(inputs, tmp_path,
                                                                      command):
    outputs = COMMANDS[command][1]
    refs = {}
    for v in "ab":
        ref = tmp_path / f"ref_{v}"
        ref.mkdir()
        rc, steps = _run(inputs, command, ref, v)
        assert rc == 0
        refs[v] = {name: _signature(ref / name) for name in outputs}
    # the variants differ in every file: a set of both is seen
    assert all(refs["a"][n] != refs["b"][n] for n in outputs), refs
    work = tmp_path / "work"
    work.mkdir()
    assert _run(inputs, command, work, "a")[0] == 0
    kills = 0
    for k in range(steps):
        variant = "ab"[k % 2]
        rc, _ = _run(inputs, command, work, variant, kill_at=k)
        assert rc == -9, (k, rc)  # killed at that step
        kills += 1
        assert _variant(work, outputs, refs), (command, k, "a torn file or a mixed set")
        main_there = (work / outputs[0]).exists()
        assert not main_there or all((work / n).exists() for n in outputs), (command, k)
    assert kills == steps >= 2
    rc, _ = _run(inputs, command, work, "b")
    assert rc == 0 and _variant(work, outputs, refs) == {"b"}
    assert all((work / n).exists() for n in outputs)
    assert not _temporaries(work), _temporaries(work)
    shutil.rmtree(tmp_path)
