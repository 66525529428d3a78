"""Conversions between napari layers and the core's objects, and the layout of results.

Layer data travel as napari *layer-data tuples* ``(data, kwargs, layer_type)``, so this
package imports neither napari nor Qt (the model reader uses it too). Layers are read
duck-typed (``layer.data``, ``layer.scale``, ``layer.features``). One concept a module:

- :mod:`.names`: the layers' names, metadata keys and the beads' statuses;
- :mod:`.frame`: where an image lies in world coordinates, and its results on its field;
- :mod:`.points`: detected beads as a Points layer and back;
- :mod:`.figure`: napari's name and colour-bar overlays of each result map;
- :mod:`.results`: the result layers of each step;
- :mod:`.bookkeeping`: the layers found again, grouped by step, replaced and removed.
"""

from .bookkeeping import (
    find_layer,
    focus_on_step,
    group_layers,
    input_images,
    is_input_image,
    remove_step,
    show_layers,
    step_layers,
)
from .figure import OVERLAYS_KEY, dress, map_tuple
from .frame import (
    Frame,
    LayerTuple,
    axis_unit,
    bead_plane,
    field_units,
    image_plane,
    on_field,
)
from .names import *  # noqa: F403 (the names are the module's whole content)
from .names import __all__ as _names
from .points import (
    FIT_VERDICTS,
    advice_layers,
    beads_from_points,
    beads_layer,
    ensure_bead_features,
    fix_ids,
    for_a_new_fit,
    hot_pixels_from_layer,
    hot_pixels_layer,
    set_statuses,
    user_beads,
)
from .results import (
    GALLERY_GAP,
    bead_fwhm_layer,
    family_layers,
    gallery_cell,
    gallery_index,
    gallery_layers,
    heldout_layers,
    operator_layers,
    psf_layers,
)

__all__ = [*_names, "FIT_VERDICTS", "Frame", "GALLERY_GAP", "LayerTuple", "OVERLAYS_KEY",
           "advice_layers", "axis_unit", "bead_fwhm_layer", "bead_plane",
           "beads_from_points", "beads_layer", "dress",
           "ensure_bead_features", "family_layers", "field_units", "find_layer", "fix_ids",
           "focus_on_step", "for_a_new_fit", "gallery_cell", "gallery_index",
           "gallery_layers", "group_layers", "heldout_layers", "hot_pixels_from_layer",
           "hot_pixels_layer", "image_plane", "input_images", "is_input_image",
           "map_tuple", "on_field", "operator_layers", "psf_layers", "remove_step",
           "set_statuses", "show_layers", "step_layers", "user_beads"]
