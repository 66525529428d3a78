"""The family of operators has one name, "family", across the API, the command line and
the panel; its old names ("subspace") still work, each use saying so once with a
FutureWarning (scikit-image's style) that names the new name."""

import numpy as np
import pytest

import napari_psfspace as ps
from napari_psfspace.cli import main
from napari_psfspace.core.common.deprecate import SINCE, UNTIL


@pytest.mark.parametrize("module, old, new", [
    ("napari_psfspace", "OperatorSubspace", "OperatorFamily"),
    ("napari_psfspace", "estimate_subspace", "estimate_family"),
    ("napari_psfspace", "iter_estimate_subspace", "iter_estimate_family"),
    ("napari_psfspace", "load_subspace", "load_family"),
    ("napari_psfspace.core.family", "OperatorSubspace", "OperatorFamily"),
    ("napari_psfspace.core.family", "estimate_subspace", "estimate_family"),
    ("napari_psfspace.core.family.result", "load_subspace", "load_family"),
    ("napari_psfspace.core.family.result", "save_subspace", "save_family"),
    ("napari_psfspace.core.family.estimate", "iter_estimate_subspace",
     "iter_estimate_family"),
    ("napari_psfspace.core.subspace.result", "load_subspace", "load_family"),
])
def test_an_old_name_is_the_new_one_with_a_warning(module, old, new):
    import importlib
    import warnings

    with warnings.catch_warnings():  # the old stage path's own warning: the test below
        warnings.simplefilter("ignore", FutureWarning)
        import napari_psfspace.core.subspace  # noqa: F401

    mod = importlib.import_module(module)
    with pytest.warns(FutureWarning) as record:
        got = getattr(mod, old)
    text = str(record[0].message)
    assert f"`{old}`" in text and f"`{new}`" in text and SINCE in text and UNTIL in text
    # the same object as the new name's, wherever the new name lives
    new_obj = getattr(mod, new) if hasattr(mod, new) else getattr(ps, new)
    assert got is new_obj
    assert not hasattr(mod, "no_such_name")  # anything else: an AttributeError


def test_identify_operator_takes_its_old_keyword_with_a_warning(monkeypatch):
    """``identify_operator(image, subspace=...)``: the same call as ``family=``."""
    from napari_psfspace.core.restore import identify

    seen = {}

    def fake(image, family, **kw):  # the decorated function's body is not the point
        seen["family"] = family
        return "operator"

    wrapped = identify.renamed_keyword("subspace", "family")(fake)
    with pytest.warns(FutureWarning, match=r"identify_operator|fake"):
        assert wrapped(np.zeros((4, 4)), subspace="F") == "operator"
    assert seen["family"] == "F"
    with pytest.raises(TypeError, match="give `family` only"):
        wrapped(np.zeros((4, 4)), subspace="F", family="G")
    # and the real function carries the decorator: its old keyword reaches the check of
    # the family's type, which names it (not Python's "unexpected keyword" TypeError)
    with pytest.warns(FutureWarning), pytest.raises(TypeError, match="`family` must be"):
        ps.identify_operator(np.zeros((32, 32)), subspace="not a family")


def test_the_command_line_takes_subspace_for_family(tmp_path, capsys):
    """``deblur --subspace`` is ``--family``: the same refusal of a model file, after one
    line that says the option is deprecated."""
    from napari_psfspace.core.model.operator import ProductConvolution

    image = tmp_path / "image.tif"
    import tifffile

    tifffile.imwrite(image, np.zeros((32, 32), np.uint16))
    model = tmp_path / "model.npz"
    ProductConvolution(np.ones((1, 3, 3)) / 9, np.ones((1, 1, 1)), shape=(32, 32),
                       grid=(np.zeros(1), np.zeros(1))).save(model)
    for option in ("--family", "--subspace"):
        code = main(["deblur", str(image), option, str(model), "-o", str(tmp_path / "x.tif")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and f"{option} {model} is not a family file" in err[-1]
        warned = [line for line in err if "FutureWarning" in line]
        assert len(warned) == (option == "--subspace")
        if warned:
            assert "`--family`" in warned[0]


def test_the_old_stage_path_is_the_new_one_with_a_warning():
    """``napari_psfspace.core.subspace`` (the stage's folder until 0.2.0) and each of its
    modules are the ``core.family`` ones; the first import says so (a fresh process)."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import warnings
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            import napari_psfspace.core.subspace.result as old_result
            from napari_psfspace.core.subspace.subspace_file import FORMAT_NAME
            from napari_psfspace.core.subspace import estimate_family
        import napari_psfspace.core.family as family
        import napari_psfspace.core.family.family_file as family_file
        import napari_psfspace.core.family.result as result
        assert old_result is result and estimate_family is family.estimate_family
        assert FORMAT_NAME == family_file.FORMAT_NAME
        future = [str(w.message) for w in seen if w.category is FutureWarning]
        assert len(future) == 1 and "`napari_psfspace.core.family`" in future[0], future
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
