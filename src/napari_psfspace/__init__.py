"""napari-psfspace: learn space-varying PSF operators from images of micro-beads.

The public API is headless (numpy / scipy / scikit-image); the napari widgets sit on
top of it. Every long computation ``NAME`` has a generator twin ``iter_NAME`` that
yields :class:`Progress` records and returns the same result (for a GUI that shows
progress and can stop). Typical use::

    import napari_psfspace as ps

    image, truth = ps.simulate_beads((1024, 1024), n_beads=150, seed=0)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    psf = op.psf_at(100.0, 900.0)        # PSF at row 100, column 900, sums to 1
    blurred = op.apply(image.astype("float32"))
    op.save("model.npz")
    op = ps.load_operator("model.npz")

One operator (:func:`estimate_operator`), its diagnosis (:func:`diagnose`), a family
of operators from many images (:func:`estimate_family`, :func:`load_family`), the
operator of the family that explains a few beads (:func:`identify_operator`) and the
deblurring with it (:func:`deblur`); from a bead z-stack, a space-varying 3D PSF
(:func:`estimate_operator_3d`).
"""

#: Where each public name lives: imported on first use (importing the package costs
#: nothing; a napari reader that opens a file loads only what the file needs).
_LAZY = {
    "Beads": ".core.beads.detect",
    "best_focus_index": ".core.beads.focus",
    "deblur": ".core.restore",
    "deblur_3d": ".core.volume",
    "Deblurred": ".core.restore",
    "detect_beads": ".core.beads.detect",
    "diagnose": ".core.diagnosis.loop",
    "Diagnosis": ".core.diagnosis.loop",
    "estimate_family": ".core.family",
    "estimate_operator": ".core.model.estimate",
    "estimate_operator_3d": ".core.volume",
    "Estimation": ".core.model.estimate",
    "extract_patches": ".core.beads.patches",
    "FieldAberrations": ".core.simulation",
    "identify_operator": ".core.restore",
    "iter_deblur": ".core.restore",
    "iter_deblur_3d": ".core.volume",
    "iter_diagnose": ".core.diagnosis.loop",
    "iter_estimate": ".core.model.estimate",
    "iter_estimate_family": ".core.family",
    "iter_estimate_operator_3d": ".core.volume",
    "iter_heldout_error": ".core.diagnosis.loop",
    "iter_richardson_lucy_3d": ".core.volume",
    "load_family": ".core.family.result",
    "load_operator": ".core.model.operator",
    "load_operator_3d": ".core.volume",
    "NoBeadsError": ".core.beads.detect",
    "OperatorFamily": ".core.family",
    "Optics": ".core.simulation",
    "Patches": ".core.beads.patches",
    "ProductConvolution": ".core.model.operator",
    "ProductConvolution3D": ".core.volume",
    "Progress": ".core.common.progress",
    "psf_error": ".core.simulation.metrics",
    "PsfSpaceError": ".core.common.errors",
    "richardson_lucy_3d": ".core.volume",
    "richardson_lucy_3d_exchange": ".core.volume",
    "richardson_lucy_3d_tiled": ".core.volume",
    "run_with_progress": ".core.common.progress",
    "simulate_beads": ".core.simulation",
    "simulate_focus_series": ".core.simulation.focus",
    "simulate_psf": ".core.simulation",
    "SimulationTruth": ".core.simulation",
    "spot_scale": ".core.beads.scale",
    "suggest_psf_radius": ".core.beads.radius",
}

__all__ = [
    "Beads",
    "Deblurred",
    "Diagnosis",
    "Estimation",
    "FieldAberrations",
    "NoBeadsError",
    "OperatorFamily",
    "Optics",
    "Patches",
    "ProductConvolution",
    "ProductConvolution3D",
    "Progress",
    "PsfSpaceError",
    "SimulationTruth",
    "__version__",
    "best_focus_index",
    "deblur",
    "deblur_3d",
    "detect_beads",
    "diagnose",
    "estimate_operator",
    "estimate_operator_3d",
    "estimate_family",
    "extract_patches",
    "identify_operator",
    "iter_deblur",
    "iter_deblur_3d",
    "iter_diagnose",
    "iter_estimate",
    "iter_estimate_operator_3d",
    "iter_estimate_family",
    "iter_heldout_error",
    "iter_richardson_lucy_3d",
    "load_operator",
    "load_operator_3d",
    "load_family",
    "psf_error",
    "richardson_lucy_3d",
    "richardson_lucy_3d_exchange",
    "richardson_lucy_3d_tiled",
    "run_with_progress",
    "simulate_beads",
    "simulate_focus_series",
    "simulate_psf",
    "spot_scale",
    "suggest_psf_radius",
]


def __getattr__(name: str):
    """A public name, imported from its module on first use; the old names of the
    family of operators ("subspace"): deprecated, still there."""
    if name == "__version__":
        from .core.common.version import package_version

        globals()[name] = package_version()
        return globals()[name]
    if name in _LAZY:
        from importlib import import_module

        value = getattr(import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    from .core.common.deprecate import module_getattr

    return module_getattr(__name__, {
        "OperatorSubspace": ("OperatorFamily", lambda: __getattr__("OperatorFamily")),
        "estimate_subspace": ("estimate_family", lambda: __getattr__("estimate_family")),
        "iter_estimate_subspace": ("iter_estimate_family",
                                   lambda: __getattr__("iter_estimate_family")),
        "load_subspace": ("load_family", lambda: __getattr__("load_family"))})(name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
