"""Command line: ``psfspace simulate | estimate | diagnose | learn | psf | apply | deblur |
estimate3d | deblur3d | demo``.

Run ``psfspace COMMAND --help`` for the options of each command. Errors in the input
(no beads, a stack without a slice, a model for another image size...) end with a
one-line message and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from . import __version__

#: ``simulate --focus-series``: the foci span +-this (micrometres).
SERIES_HALF_RANGE_UM = 0.6
#: How long ``learn --scheduler`` waits for the scheduler to answer.
SCHEDULER_TIMEOUT = "10s"


def _progress_printer(stream=None):
    start = time.perf_counter()
    last: list = []

    def show(p):
        if last == [p]:  # a long step's repeated record (it is still running)
            return
        last[:] = [p]
        print(f"[{100 * p.fraction:5.1f}% {time.perf_counter() - start:6.1f}s] {p.stage}: "
              f"{p.message}", file=stream or sys.stderr, flush=True)

    return show


def _number(kind: str, *, low: float | None = None, high: float | None = None,
            low_open: bool = False, high_open: bool = False):
    """An argparse ``type`` for a finite number in a range: a bad value makes argparse
    name the option and exit 2 before any work."""
    def parse(text: str):
        try:
            v = int(text) if kind == "int" else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'a whole number' if kind == 'int' else 'a number'}, got "
                f"{text!r}") from None
        bad = not np.isfinite(v)
        if low is not None:
            bad |= v <= low if low_open else v < low
        if high is not None:
            bad |= v >= high if high_open else v > high
        if bad:
            lo = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
            hi = "" if high is None else f"{'<' if high_open else '<='} {high:g}"
            raise argparse.ArgumentTypeError(
                f"expected a finite number {' and '.join(x for x in (lo, hi) if x)}, got "
                f"{text!r}")
        return v
    parse.__name__ = kind  # argparse's "invalid <name> value" when it is not ours
    return parse


POSITIVE = _number("float", low=0, low_open=True)
NON_NEGATIVE = _number("float", low=0)
FINITE = _number("float")
COUNT = _number("int", low=1)
INDEX = _number("int", low=0)


def _n_psf(text: str):
    """--n-psf: a whole number >= 1, or 'heldout' / 'rule'."""
    if text in ("heldout", "rule"):
        return text
    try:
        return COUNT(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number >= 1, 'heldout' or 'rule', got {text!r}") from None


def _existing(path: str, option: str) -> str:
    """An input file that must exist (checked before any work)."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {path}: is a folder, expected a file")
    if not p.exists():
        raise ValueError(f"{option} {path}: no such file")
    return path


def _cmd_simulate(args) -> int:
    from .core.simulation import simulate_beads
    from .io import check_output_file, write_tiff

    check_output_file(args.output, "-o")
    if args.truth_grid:
        check_output_file(args.truth_grid, "--truth-grid")
    if args.focus_series:
        if args.truth_grid:
            raise ValueError("--truth-grid is for one image; a --focus-series has one "
                             "PSF field per slice")
        return _simulate_series(args)
    image, truth = simulate_beads(tuple(args.shape), args.beads, aberrations=args.aberrations,
                                  seed=args.seed)
    meta = {"psf_radius": truth.psf_radius, "n_beads": int(len(truth.positions)),
            "aberrations": args.aberrations, "seed": args.seed}
    write_tiff(args.output, image, pixel_size=truth.optics.pixel_size, metadata=meta)
    print(f"wrote {args.output}: {image.shape[0]}x{image.shape[1]} {image.dtype}, "
          f"{len(truth.positions)} beads, suggested --psf-radius {truth.psf_radius}")
    if args.truth_grid:
        ys, xs, psfs = truth.psf_grid(8, 8)
        write_tiff(args.truth_grid, psfs.reshape(-1, *psfs.shape[2:]))
        print(f"wrote {args.truth_grid}: true PSFs on an 8x8 grid")
    return 0


def _simulate_series(args) -> int:
    """``simulate --focus-series N``: one bead field at N foci from -0.6 to 0.6 µm."""
    from .core.simulation.focus import simulate_focus_series
    from .io import write_tiff

    z_um = np.linspace(-SERIES_HALF_RANGE_UM, SERIES_HALF_RANGE_UM, args.focus_series)
    stack, series = simulate_focus_series(tuple(args.shape), args.beads, z_um,
                                          aberrations=args.aberrations, seed=args.seed)
    meta = {"psf_radius": int(series.psf_radius.max()), "z_um": series.z_um.tolist(),
            "n_beads": args.beads, "aberrations": args.aberrations, "seed": args.seed}
    write_tiff(args.output, stack, pixel_size=series.optics.pixel_size, metadata=meta)
    print(f"wrote {args.output}: {stack.shape[0]} slices of {stack.shape[1]}x"
          f"{stack.shape[2]} {stack.dtype} at foci {z_um[0]:+.2f} to {z_um[-1]:+.2f} um, "
          f"{args.beads} beads; widest PSF radius {meta['psf_radius']} px")
    return 0


def _psf_radius_px(args, info) -> float | None:
    if args.psf_radius is not None:
        return args.psf_radius
    if args.psf_radius_um is not None:
        if not info.pixel_size:
            raise ValueError(
                "--psf-radius-um needs the pixel size, which the file does not give: "
                "pass --psf-radius in pixels instead."
            )
        return args.psf_radius_um / info.pixel_size
    return None


def _image_and_radius(args):
    """The image (a slice of a stack), what the file says of it, and the PSF radius in
    pixels: given in pixels or micrometres, else measured from the image."""
    from .io import read_image

    image, info = read_image(args.image, index=args.slice)
    if getattr(args, "pixel_size_nm", None) is not None:
        if not args.pixel_size_nm > 0:
            raise ValueError(f"--pixel-size-nm must be > 0, got {args.pixel_size_nm}.")
        info = dataclasses.replace(info, pixel_size=args.pixel_size_nm / 1000.0)
    r = _psf_radius_px(args, info)
    if r is None:
        from .core.beads.scale import suggest_psf_radius

        r = suggest_psf_radius(image)
        print(f"no --psf-radius given: using {r:g} px, measured from the image "
              "(see suggest_psf_radius)", file=sys.stderr)
        if args.slice is not None:  # a slice of a stack: against the slice in focus
            from .core.beads.scale import radius_against_focus
            from .io import read_stack

            why = radius_against_focus(read_stack(args.image)[0], args.slice, r)
            if why:
                print(why, file=sys.stderr)
    return image, info, r


def _bead_diameter_px(args, info) -> float:
    """--bead-diameter-nm in pixels (0 without it), with the image's pixel size."""
    d = getattr(args, "bead_diameter_nm", None)
    if d is None:
        return 0.0
    if not d >= 0:
        raise ValueError(f"--bead-diameter-nm must be >= 0, got {d}.")
    if not info.pixel_size:
        raise ValueError("--bead-diameter-nm needs the pixel size, which the file does not "
                         "give: pass --pixel-size-nm too.")
    return d / 1000.0 / info.pixel_size


def _cmd_estimate(args) -> int:
    from .core.common.measures import field_fwhm, fwhm_line
    from .core.common.progress import run_with_progress
    from .core.diagnosis.loop import iter_heldout_error
    from .core.model.estimate import iter_estimate
    from .io import check_output_file
    from .report import model_lines

    check_output_file(args.output, "-o")
    image, info, r = _image_and_radius(args)
    n_psf = args.n_psf
    gen = iter_estimate(image, psf_radius=r, n_psf=n_psf, smoothing=args.smoothing,
                        threshold=args.threshold, holdout=args.holdout or None,
                        bead_diameter=_bead_diameter_px(args, info),
                        remove_motion=args.remove_motion)
    est = run_with_progress(gen, None if args.quiet else _progress_printer())
    # the one accuracy figure (core/diagnosis/metric.py), by the code Diagnose uses
    try:
        held = run_with_progress(
            iter_heldout_error(image, psf_radius=r, threshold=args.threshold,
                               n_psf=n_psf if isinstance(n_psf, int) else None,
                               smoothing=args.smoothing,
                               bead_diameter=_bead_diameter_px(args, info)),
            None if args.quiet else _progress_printer())
    except ValueError as exc:  # e.g. too few beads to judge each by the others
        held = str(exc)
    op = est.operator
    op = type(op)(op.basis, op.coefficients, shape=op.shape, grid=op.grid,
                  metadata={**op.metadata, "heldout_error": (
                      held if isinstance(held, str) else held.to_dict()),
                            **({"pixel_size_um": info.pixel_size, "source": str(args.image),
                                "slice": args.slice} if info.pixel_size else {})})
    op.save(args.output)
    meta = op.metadata
    print(f"wrote {args.output}: basis of {op.n_psf} PSFs of {op.psf_size} px from "
          f"{meta['n_beads_used']} beads; {est.beads.summary()}")
    print(f"held-out error not measured: {held}" if isinstance(held, str) else held.line())
    for line in model_lines(meta, markdown=False):
        print(line)
    print(fwhm_line(field_fwhm(op), info.pixel_size))
    return 0


def _cmd_diagnose(args) -> int:
    from .core.common.measures import field_fwhm, fwhm_line
    from .core.common.progress import run_with_progress
    from .core.diagnosis.loop import iter_diagnose
    from .io import check_output_file, check_output_folder
    from .report import model_lines, summary_text, write_report

    if args.read_noise is not None and args.gain is None:
        raise ValueError("--read-noise needs --gain and --offset: give the three camera "
                         "values together (or only --offset).")
    check_output_folder(args.report, "--report")
    if args.model:
        check_output_file(args.model, "--model")
    image, info, r = _image_and_radius(args)
    gen = iter_diagnose(image, psf_radius=r, threshold=args.threshold, gain=args.gain,
                        offset=args.offset, read_noise=args.read_noise, n_psf=args.n_psf,
                        smoothing=args.smoothing, bead_diameter=_bead_diameter_px(args, info),
                        remove_motion=args.remove_motion)
    diag = run_with_progress(gen, None if args.quiet else _progress_printer(sys.stderr))
    print(summary_text(diag))
    for line in model_lines(diag.operator.metadata, markdown=False):
        print(line)
    print(fwhm_line(field_fwhm(diag.operator), info.pixel_size))
    extra = {"source": str(args.image), "slice": args.slice}
    path = write_report(diag, args.report, image_name=Path(args.image).name,
                        pixel_size=info.pixel_size, extra=extra)
    print(f"wrote {path} with report.json and figures in {path.parent}/")
    if args.model:
        op = diag.operator
        op = type(op)(op.basis, op.coefficients, shape=op.shape, grid=op.grid,
                      metadata={**op.metadata, "pixel_size_um": info.pixel_size, **extra})
        op.save(args.model)
        print(f"wrote {args.model}: refined model, basis of {op.n_psf} PSFs of "
              f"{op.psf_size} px")
    return 0


def _cmd_learn(args) -> int:
    from .core.beads.scale import suggest_psf_radius
    from .core.common.progress import run_with_progress
    from .core.subspace import iter_estimate_subspace
    from .core.subspace.estimate import max_space
    from .io import check_output_file, read_image, read_slice, stack_loaders

    check_output_file(args.output, "-o")
    loaders, labels = stack_loaders(args.inputs, args.slices)
    if len(loaders) < 2:
        raise ValueError(f"learn needs at least 2 images (conditions), got {len(loaders)}: "
                         "pass several TIFFs, a folder, or a stack (with --slices)")
    r = args.psf_radius
    if r is None:
        _, info = read_image(loaders[0].args[0], index=loaders[0].args[1])
        if args.psf_radius_um is not None:
            if not info.pixel_size:
                raise ValueError("--psf-radius-um needs the pixel size, which the file does "
                                 "not give: pass --psf-radius in pixels instead.")
            r = args.psf_radius_um / info.pixel_size
        else:
            # the middle image first, then outwards: a stack's ends are often out of focus
            # or empty, where no radius can be measured
            n = len(loaders)
            for i in sorted(range(n), key=lambda j: abs(j - n // 2))[:7]:
                try:
                    r = suggest_psf_radius(read_slice(*loaders[i].args))
                except ValueError:
                    continue
                print(f"no --psf-radius given: using {r:g} px, measured from {labels[i]}",
                      file=sys.stderr)
                break
            else:
                raise ValueError("no --psf-radius given and none could be measured on the "
                                 "middle images (no bright spot stands out of the noise): "
                                 "give --psf-radius")
    most = max_space(len(loaders), args.n_psf, psf_radius=r)
    if args.n_space is not None and args.n_space > most:
        raise ValueError(f"--n-space {args.n_space} is more spatial maps than {len(loaders)} "
                         f"images give: at most {most}")
    client = None
    if args.scheduler:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("--scheduler needs dask.distributed: pip install "
                             "'napari-psfspace[cluster]'") from None
        try:
            client = Client(args.scheduler, timeout=SCHEDULER_TIMEOUT)
        except (OSError, TimeoutError) as exc:
            raise ValueError(f"--scheduler {args.scheduler}: no dask scheduler answered "
                             f"within {SCHEDULER_TIMEOUT} ({type(exc).__name__})") from None
    try:
        gen = iter_estimate_subspace(loaders, psf_radius=r, n_psf=args.n_psf,
                                     n_space=args.n_space, client=client,
                                     threshold=args.threshold)
        sub = run_with_progress(gen, None if args.quiet else _progress_printer())
    finally:
        if client is not None:
            client.close()
    sub.metadata["inputs"] = [labels[k] for k in sub.metadata["images"]]
    sub.save(args.output)
    m = sub.metadata
    print(f"wrote {args.output}: {sub.n_images} images, I = {sub.n_psf} PSFs, J = "
          f"{sub.n_space} spatial maps, {sum(m['beads_per_image'])} beads")
    for k, why in m["skipped"].items():
        print(f"skipped {labels[int(k)]}: {why}")
    return 0


def _cmd_psf(args) -> int:
    from .core.model.operator import load_operator
    from .core.model.operator_file import archive_format
    from .core.subspace.subspace_file import FORMAT_NAME as SUBSPACE
    from .core.subspace.subspace_file import load_subspace
    from .io import check_output_file, write_tiff

    _existing(args.model, "MODEL")
    check_output_file(args.output, "-o")
    if archive_format(args.model) == SUBSPACE:
        sub = load_subspace(args.model)
        if args.image is None:
            raise ValueError(f"{args.model} is a subspace of {sub.n_images} images: pass "
                             f"--image K (0 to {sub.n_images - 1})")
        if not args.image < sub.n_images:
            raise ValueError(f"--image {args.image} is out of range: {args.model} holds "
                             f"{sub.n_images} images (0 to {sub.n_images - 1})")
        op = sub.operator(args.image)
    elif args.image is not None:
        raise ValueError(f"--image is for a subspace; {args.model} is a single model")
    else:
        op = load_operator(args.model)
    y, x = args.at
    from .core.model.psf_field import check_in_field

    try:
        check_in_field(y, x, op.shape)
    except ValueError as exc:
        raise ValueError(f"--at {y} {x}: {str(exc).split(' = ', 1)[-1]}") from None
    psf = op.psf_at(y, x)
    write_tiff(args.output, psf, pixel_size=op.metadata.get("pixel_size_um"),
               metadata={"row": y, "column": x})
    print(f"wrote {args.output}: PSF at row {y}, column {x} ({psf.shape[0]}x{psf.shape[1]}, "
          "sum 1)")
    return 0


def _cmd_deblur(args) -> int:
    from .core.common.progress import run_with_progress
    from .core.model.operator import load_operator
    from .core.model.operator_file import archive_format
    from .core.restore import identify_operator, iter_deblur
    from .core.restore.identify import IdentificationWarning
    from .core.subspace.subspace_file import FORMAT_NAME as SUBSPACE
    from .core.subspace.subspace_file import load_subspace
    from .io import check_output_file, read_image, read_points_csv, write_tiff

    out = check_output_file(args.output, "-o")
    if args.parts:
        for name in ("sparse", "smooth"):
            check_output_file(out.with_name(f"{out.stem}.{name}{out.suffix or '.tif'}"),
                              "--parts")
    if args.subspace is not None:
        _existing(args.subspace, "--subspace")
    else:
        _existing(args.model, "--model")
        if args.beads:
            raise ValueError("--beads identifies an operator of a --subspace; with --model "
                             "the model is used as it is")
    if args.beads:
        _existing(args.beads, "--beads")
    from .core.common.device import array_module

    device = array_module(args.device)  # gpu without CuPy or a device: one line, no work
    image, info = read_image(args.image, index=args.slice)
    t0 = time.perf_counter()
    if args.subspace is not None:
        if archive_format(args.subspace) not in (SUBSPACE, None):  # None: for the reader
            raise ValueError(f"--subspace {args.subspace} is not a subspace file (learn one "
                             "with psfspace learn); a single model goes with --model")
        sub = load_subspace(args.subspace)
        beads = read_points_csv(args.beads) if args.beads else None
        with warnings.catch_warnings():  # said below, once
            warnings.simplefilter("ignore", IdentificationWarning)
            op = identify_operator(image, sub, beads=beads)
        ident = op.metadata["identification"]
        spread = ident.get("psf_spread")
        print(f"operator identified from {ident['n_beads']} beads "
              f"({'given' if beads is not None else 'detected'}; the family's J = "
              f"{sub.n_space}{'' if ident['enough_beads'] else ': fewer beads than J'}) "
              f"in {time.perf_counter() - t0:.1f} s; error on them beyond the noise "
              f"{ident['model_error']:.3f}"
              + ("" if spread is None else f", PSF spread {spread:.3f} (relative, mean "
                                           "over the field)"), file=sys.stderr)
        if ident.get("warning"):
            print(f"WARNING: {ident['warning']}", file=sys.stderr)
    else:
        op = load_operator(args.model)
    gen = iter_deblur(image, op, sparse_weight=args.sparse_weight,
                      smooth_weight=args.smooth_weight, max_iter=args.max_iter,
                      debias=args.refit_amplitudes, device=device)
    res = run_with_progress(gen, None if args.quiet else _progress_printer())
    write_tiff(out, res.image, pixel_size=info.pixel_size,
               metadata={"deblur": res.parameters, "iterations": res.iterations})
    written = [str(out)]
    p = res.parameters
    if args.parts:
        for name, part in (("sparse", res.sparse), ("smooth", res.smooth)):
            path = out.with_name(f"{out.stem}.{name}{out.suffix or '.tif'}")
            write_tiff(path, part, pixel_size=info.pixel_size)
            written.append(str(path))
    print(f"wrote {', '.join(written)}: {res.iterations} iterations on the "
          f"{p['device'].upper()} "
          f"({'converged' if res.converged else 'max_iter reached'}), sparse weight "
          f"{p['sparse_weight']:.3g}, smooth weight {p['smooth_weight']:.3g}, noise sd "
          f"{p['noise_sd']:.3g}, {time.perf_counter() - t0:.1f} s"
          + (f"; {p['saturated_pixels']} saturated pixels (>= {p['saturation']:g}) fitted "
             "as lower bounds" if p["saturated_pixels"] else ""))
    return 0


def _cmd_apply(args) -> int:
    from .core.model.operator import load_operator
    from .io import check_output_file, read_image, write_tiff

    _existing(args.model, "MODEL")
    check_output_file(args.output, "-o")
    op = load_operator(args.model)
    image, info = read_image(args.image, index=args.slice)
    if tuple(image.shape) != tuple(op.shape):
        raise ValueError(f"IMAGE {args.image} has shape {tuple(image.shape)}, the model "
                         f"{args.model} acts on images of shape {tuple(op.shape)}")
    t0 = time.perf_counter()
    out = op.adjoint(image.astype(np.float32)) if args.adjoint else op.apply(
        image.astype(np.float32))
    write_tiff(args.output, out, pixel_size=info.pixel_size)
    print(f"wrote {args.output}: {'adjoint' if args.adjoint else 'blurred'} image "
          f"({time.perf_counter() - t0:.2f} s)")
    return 0


def _cmd_estimate3d(args) -> int:
    from .core.common.measures import NAMES, in_units
    from .core.common.progress import run_with_progress
    from .core.volume import iter_estimate_operator_3d
    from .core.volume.measures import (
        bead_measures,
        map_uncertainty,
        measure_maps,
        measure_table,
    )
    from .io import check_output_file, read_stack

    check_output_file(args.output, "-o")
    if args.table:
        check_output_file(args.table, "--table")
    stack, info = read_stack(args.stack)
    pixel = args.pixel_size_nm / 1000.0 if args.pixel_size_nm else info.pixel_size
    dz = args.z_step_nm / 1000.0 if args.z_step_nm else info.z_spacing
    if args.psf_radius is not None:
        r = args.psf_radius
    elif not pixel:
        raise ValueError("--psf-radius-um needs the pixel size, which the file does not "
                         "give: pass --pixel-size-nm or --psf-radius in pixels")
    else:
        r = args.psf_radius_um / pixel
    voxel = (dz, pixel, pixel) if pixel and dz else None
    est = run_with_progress(iter_estimate_operator_3d(
        stack, psf_radius=r, z_radius=args.z_radius, n_psf=args.n_psf,
        threshold=args.threshold, voxel_size=voxel),
        None if args.quiet else _progress_printer())
    op = est.operator
    op.save(args.output)
    inl = est.basis.inliers
    beads = bead_measures(est.patches.subset(inl))
    unc = map_uncertainty(op, beads, est.patches.centers[inl])
    _, _, maps = measure_maps(op, 4, 4)
    print(f"wrote {args.output}: {op.n_psf} 3D PSFs of {'x'.join(map(str, op.kernel_shape))} "
          f"voxels from {op.metadata['n_beads_used']} beads, bead plane {op.plane}")
    print("  measures (Gaussian fits with an offset, as napari-psf-analysis quotes them; "
          + ("nm" if voxel else "px and planes: pass --pixel-size-nm and --z-step-nm for nm")
          + "):")
    for name in NAMES:
        lo, lo_u = in_units({name: float(np.nanmin(maps[name]))}, voxel)
        hi, _ = in_units({name: float(np.nanmax(maps[name]))}, voxel)
        sd, _ = in_units({name: unc[name]}, voxel)
        unit = f" {lo_u[name]}" if lo_u[name] else ""
        what = "focal_plane (from the first plane)" if name == "focal_plane" else name
        if not np.isfinite(lo[name]):
            print(f"  {what}: not measurable over the field")
            continue
        spread = (f"+- {sd[name]:.2g} between the beads and the model"
                  if np.isfinite(sd[name]) else "fewer than 3 beads to compare with the model")
        print(f"  {what}: {lo[name]:.3g} to {hi[name]:.3g}{unit} over the field ({spread})")
    held = op.metadata.get("heldout")
    if held and held.get("n_beads"):
        print(f"  held-out beads ({held['n_beads']}): residual {held['residual_median']:.3f}, "
              f"{held['over_floor']:.2f}x their noise floor ({held['noise_kind']}); one 3D "
              f"PSF {held['single_median']:.3f}")
    if op.metadata.get("field_model") == "shift-invariant":
        print(f"  one 3D PSF for the field: {op.metadata['field_model_reason']}")
    if args.table:
        import csv

        from .core.common.atomic import atomic_write

        rows = measure_table(beads, est.patches.centers[inl], voxel)

        def write(fh):
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

        atomic_write(args.table, write, mode="w", encoding="utf-8", newline="")
        print(f"wrote {args.table}: {len(rows)} beads' direct fits")
    return 0


def _cmd_deblur3d(args) -> int:
    from .core.common.progress import run_with_progress
    from .core.volume import load_operator_3d
    from .core.volume.deconvolve3d import iter_richardson_lucy_3d
    from .core.volume.fista3d import iter_deblur_3d
    from .core.volume.tiles3d import richardson_lucy_3d_tiled
    from .io import check_output_file, read_stack, write_tiff

    _existing(args.model, "--model")
    check_output_file(args.output, "-o")
    if args.scheduler and not args.tile:
        raise ValueError("--scheduler runs tiles: give --tile too")
    if args.method == "sparse" and args.tile:
        raise ValueError("--tile runs Richardson-Lucy only: drop --tile, or use --method rl")
    from .core.common.device import array_module

    if args.device == "gpu" and args.tile:
        raise ValueError("--device gpu runs on the whole stack (its blocks sized from the "
                         "GPU's memory): drop --tile, or use --device cpu")
    device = array_module("cpu" if args.tile else args.device)
    op = load_operator_3d(args.model)
    stack, info = read_stack(args.stack)
    if stack.shape[1:] != op.shape[1:]:
        raise ValueError(f"STACK {args.stack} has slices of {stack.shape[1:]}, the model "
                         f"{args.model} acts on {op.shape[1:]}")
    t0 = time.perf_counter()
    printer = None if args.quiet else _progress_printer()
    from .core.volume.blocks3d import RTOL

    rtol = RTOL if args.rtol is None else args.rtol
    meta: dict = {"method": args.method, "rtol": rtol}
    if args.method == "sparse":
        res = run_with_progress(iter_deblur_3d(stack, op, max_iter=args.iterations,
                                               rtol=rtol, device=device), printer)
        volume = res.volume
        meta.update(iterations=res.iterations, converged=res.converged,
                    sparse_weight=res.parameters["sparse_weight"],
                    smooth_weight=res.parameters["smooth_weight"],
                    device=res.parameters["device"])
        what = (f"{res.iterations} sparse + smooth iterations on the "
                f"{res.parameters['device'].upper()} "
                f"({'converged' if res.converged else 'stopped at the limit'})")
    elif args.tile:
        client = None
        if args.scheduler:
            from distributed import Client

            client = Client(args.scheduler, timeout=SCHEDULER_TIMEOUT)
        try:
            volume = richardson_lucy_3d_tiled(stack, op, n_iter=args.iterations,
                                              background=args.background, tile=args.tile,
                                              rtol=rtol, client=client)
        finally:
            if client is not None:
                client.close()
        meta.update(iterations=args.iterations, tile=args.tile)
        what = f"{args.iterations} Richardson-Lucy iterations on {args.tile} px tiles"
    else:
        res = run_with_progress(iter_richardson_lucy_3d(stack, op, n_iter=args.iterations,
                                                        background=args.background,
                                                        rtol=rtol, device=device), printer)
        volume = res.volume
        meta.update(iterations=res.iterations, background=res.background, device=res.device)
        what = f"{res.iterations} Richardson-Lucy iterations on the {res.device.upper()}"
    write_tiff(args.output, volume, pixel_size=info.pixel_size, metadata={"deblur3d": meta})
    print(f"wrote {args.output}: {what} with the space-varying 3D PSF, "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def _cmd_demo(args) -> int:
    from .demo import format_table, run_demo
    from .io import check_output_folder

    check_output_folder(args.out, "--out")
    result = run_demo(args.out, scene=args.scene, seed=args.seed,
                      progress=None if args.quiet else _progress_printer())
    print(format_table(result))
    print(f"\nfigures, TIFFs, model and errors.json in {args.out}/")
    if args.json:
        print(json.dumps(result["errors"], indent=2))
    return 0


def _add_radius_and_slice(parser: argparse.ArgumentParser) -> None:
    """--psf-radius / --psf-radius-um (default: measured from the image), --slice,
    --pixel-size-nm and --bead-diameter-nm."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--psf-radius", type=POSITIVE,
                   help="PSF radius r in pixels (default: suggested from the image)")
    g.add_argument("--psf-radius-um", type=POSITIVE,
                   help="PSF radius in micrometres (needs the pixel size in the TIFF)")
    parser.add_argument("--slice", type=INDEX, help="slice of a stack to use (from 0)")
    parser.add_argument("--pixel-size-nm", type=POSITIVE,
                        help="pixel size in nanometres (overrides the file's)")
    parser.add_argument("--bead-diameter-nm", type=NON_NEGATIVE,
                        help="bead diameter in nanometres (from the beads' data sheet): "
                             "divided out of the learnt PSFs (needs the pixel size)")
    parser.add_argument("--remove-motion", action="store_true",
                        help="divide a motion blur found in the beads (a smear common to "
                             "all of them) out of the model; use when the sample was still "
                             "(motion blur is always looked for and reported)")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: the option and what is wrong, then where to look
    (the usage block would bury the line that matters)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="psfspace",
        description="Learn space-varying PSF operators from images of fluorescent beads.",
    )
    p.add_argument("--version", action="version", version=f"napari-psfspace {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a bead image with a known PSF field")
    s.add_argument("-o", "--output", required=True, help="output TIFF")
    s.add_argument("--shape", type=_number("int", low=16), nargs=2, default=(1024, 1024),
                   metavar=("ROWS", "COLS"))
    s.add_argument("--beads", type=COUNT, default=150, help="number of beads (default 150)")
    s.add_argument("--aberrations", choices=("none", "moderate", "strong"), default="moderate")
    s.add_argument("--seed", type=INDEX, default=0)
    s.add_argument("--truth-grid", help="also write the true PSFs on an 8x8 grid to this TIFF")
    s.add_argument("--focus-series", type=_number("int", low=2), metavar="N",
                   help="write a stack instead: the same beads at N foci from -0.6 to "
                        "0.6 um (a family of conditions for `psfspace learn`)")
    s.set_defaults(func=_cmd_simulate)

    e = sub.add_parser("estimate", help="estimate the operator from a bead image")
    e.add_argument("image", help="TIFF bead image (2-D, or a stack with --slice)")
    e.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    _add_radius_and_slice(e)
    e.add_argument("--n-psf", type=_n_psf, help="basis size I, or 'heldout' (default) or 'rule'")
    e.add_argument("--smoothing", type=NON_NEGATIVE,
                   help="thin-plate smoothing eta (default: LOO CV)")
    e.add_argument("--threshold", type=POSITIVE, default=8.0,
                   help="detection threshold in noise standard deviations (default 8)")
    e.add_argument("--holdout", type=_number("float", low=0, high=0.5), default=0.2,
                   help="fraction of beads held out to measure the error (0 to skip)")
    e.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    e.set_defaults(func=_cmd_estimate)

    dg = sub.add_parser("diagnose", help="trace the model's held-out residual to what it "
                        "lacks, add it, write a report")
    dg.add_argument("image", help="TIFF bead image in ADU (2-D, or a stack with --slice)")
    dg.add_argument("--report", required=True, metavar="DIR",
                    help="folder for report.md, report.json and the figures")
    _add_radius_and_slice(dg)
    dg.add_argument("--gain", type=POSITIVE,
                    help="camera gain in ADU per electron (with --offset and --read-noise; "
                         "default: noise model measured on the image)")
    dg.add_argument("--offset", type=FINITE, help="camera offset in ADU")
    dg.add_argument("--read-noise", type=NON_NEGATIVE, help="camera read noise in electrons rms")
    dg.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    dg.add_argument("--n-psf", type=COUNT, help="diagnose a model of this basis size "
                    "(default: chosen from the beads)")
    dg.add_argument("--smoothing", type=NON_NEGATIVE, help="diagnose a model of this thin-plate "
                    "smoothing (default: chosen from the beads)")
    dg.add_argument("--model", metavar="OUT.npz", help="also save the refined model")
    dg.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    dg.set_defaults(func=_cmd_diagnose)

    ln = sub.add_parser("learn", help="learn the subspace of a microscope's operators from "
                        "bead images under many conditions")
    ln.add_argument("inputs", nargs="+", metavar="INPUT",
                    help="TIFF images (one per condition), a folder of them, or a stack "
                         "whose slices are the conditions")
    ln.add_argument("-o", "--output", required=True, help="subspace file to write (.npz)")
    g = ln.add_mutually_exclusive_group()
    g.add_argument("--psf-radius", type=POSITIVE,
                   help="PSF radius r in pixels (default: suggested from the first image)")
    g.add_argument("--psf-radius-um", type=POSITIVE,
                   help="PSF radius in micrometres (needs the pixel size in the TIFF)")
    ln.add_argument("--slices", metavar="A:B", help="slices A to B-1 of a stack")
    ln.add_argument("--n-psf", type=COUNT, help="PSF basis size I (default: Gavish-Donoho)")
    ln.add_argument("--n-space", type=COUNT, help="spatial basis size J (default: the rule)")
    ln.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    ln.add_argument("--scheduler", metavar="ADDRESS",
                    help="run on this dask.distributed scheduler (default: this machine)")
    ln.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    ln.set_defaults(func=_cmd_learn)

    f = sub.add_parser("psf", help="write the PSF of a model (or of image K of a subspace) "
                       "at a field position")
    f.add_argument("model", help="model or subspace file (.npz)")
    f.add_argument("--image", type=INDEX, metavar="K", help="image K of a subspace")
    f.add_argument("--at", type=FINITE, nargs=2, required=True, metavar=("ROW", "COL"))
    f.add_argument("-o", "--output", required=True, help="output TIFF")
    f.set_defaults(func=_cmd_psf)

    a = sub.add_parser("apply", help="blur an image with a model (H u), or --adjoint")
    a.add_argument("model", help="model file (.npz)")
    a.add_argument("image", help="TIFF image of the model's shape")
    a.add_argument("-o", "--output", required=True, help="output TIFF (float32)")
    a.add_argument("--slice", type=INDEX, help="slice of a stack to use")
    a.add_argument("--adjoint", action="store_true", help="apply the adjoint H^T instead")
    a.set_defaults(func=_cmd_apply)

    db = sub.add_parser("deblur", help="deblur point sources on a smooth background: with "
                        "an operator identified from a subspace (blind) or a model")
    db.add_argument("image", help="TIFF image (a slice of a stack with --slice)")
    src = db.add_mutually_exclusive_group(required=True)
    src.add_argument("--subspace", metavar="FILE", help="family of operators (psfspace "
                     "learn): the image's operator is identified from its beads")
    src.add_argument("--model", metavar="FILE", help="one operator (psfspace estimate)")
    db.add_argument("--beads", metavar="CSV", help="bead positions to identify from "
                    "(napari Points CSV or row,column; default: detected)")
    db.add_argument("--slice", type=INDEX, help="slice of a stack to deblur")
    db.add_argument("-o", "--output", required=True, help="deblurred image (TIFF, float32: "
                    "sparse + smooth parts)")
    db.add_argument("--parts", action="store_true", help="also write OUT.sparse.tif and "
                    "OUT.smooth.tif")
    db.add_argument("--sparse-weight", type=NON_NEGATIVE, help="gamma1 (default: from the noise)")
    db.add_argument("--smooth-weight", type=NON_NEGATIVE, help="gamma2 (default: 0.05 step^4)")
    db.add_argument("--max-iter", type=COUNT, default=500)
    db.add_argument("--refit-amplitudes", action="store_true",
                    help="then refit each cluster of points' flux by least squares (the l1 "
                         "term shrinks it; also raises spurious points: see deblur's "
                         "`debias`)")
    db.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                    help="where the operator's transforms run; auto (default): the GPU "
                         "when CuPy sees one (pip install 'napari-psfspace[gpu]'), else "
                         "the CPU")
    db.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    db.set_defaults(func=_cmd_deblur)

    e3 = sub.add_parser("estimate3d", help="learn the space-varying 3D PSF from a bead "
                        "z-stack; print its maps (focal shift, FWHM, astigmatism)")
    e3.add_argument("stack", help="TIFF z-stack of beads on a coverslip (Z, Y, X)")
    e3.add_argument("-o", "--output", required=True, help="3D model file to write (.npz)")
    g = e3.add_mutually_exclusive_group(required=True)
    g.add_argument("--psf-radius", type=POSITIVE,
                   help="lateral PSF radius on the widest plane used, pixels")
    g.add_argument("--psf-radius-um", type=POSITIVE, help="the same in micrometres")
    e3.add_argument("--z-radius", type=COUNT, help="planes kept on each side of the bead "
                    "plane (default: the whole stack)")
    e3.add_argument("--n-psf", type=COUNT, help="basis size I (default: held-out beads)")
    e3.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    e3.add_argument("--pixel-size-nm", type=POSITIVE, help="pixel size (overrides the file's)")
    e3.add_argument("--z-step-nm", type=POSITIVE, help="plane spacing (overrides the file's)")
    e3.add_argument("--table", metavar="CSV", help="also write each bead's direct fits")
    e3.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    e3.set_defaults(func=_cmd_estimate3d)

    d3 = sub.add_parser("deblur3d", help="deblur a z-stack with a space-varying 3D PSF "
                        "(Richardson-Lucy with H and H^T)")
    d3.add_argument("stack", help="TIFF z-stack of the model's lateral size")
    d3.add_argument("--model", required=True, metavar="FILE",
                    help="3D model (psfspace estimate3d)")
    d3.add_argument("-o", "--output", required=True, help="deblurred stack (TIFF, float32)")
    d3.add_argument("--method", choices=("rl", "sparse"), default="rl",
                    help="rl: Richardson-Lucy with H and H^T (default); sparse: sparse + "
                         "smooth (points and a smooth background)")
    d3.add_argument("--iterations", type=COUNT, default=50,
                    help="iterations (sparse: at most)")
    d3.add_argument("--background", type=FINITE,
                    help="rl: constant background (default: the stack's 1st percentile)")
    d3.add_argument("--rtol", type=NON_NEGATIVE,
                    help="largest relative error of a block's PSF against the model's "
                         "(fewer kernels a block; 0: exact; default: the library's, "
                         "napari_psfspace.core.volume.blocks3d.RTOL)")
    d3.add_argument("--tile", type=COUNT,
                    help="rl on lateral tiles of this size through dask (a stack larger "
                         "than memory; 0: the whole stack at once)")
    d3.add_argument("--scheduler", metavar="ADDRESS",
                    help="with --tile: a dask.distributed scheduler to run the tiles on")
    d3.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                    help="where it runs; auto (default): the GPU when CuPy sees one "
                         "(pip install 'napari-psfspace[gpu]'), else the CPU")
    d3.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d3.set_defaults(func=_cmd_deblur3d)

    d = sub.add_parser("demo", help="simulate a wide field, estimate, report errors, draw")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--scene", choices=("wide", "moderate", "small"), default="wide",
                   help="wide: 2048x2048, 400 beads, strong aberrations (default)")
    d.add_argument("--seed", type=INDEX, default=0)
    d.add_argument("--json", action="store_true", help="also print the errors as JSON")
    d.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``psfspace``; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad option (said in one line)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return args.func(args)
    except FileNotFoundError as exc:
        print(f"psfspace {args.command}: error: {exc.filename}: no such file", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        msg = " ".join(str(exc).split())  # one line
        print(f"psfspace {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
