"""Conversions between napari layers and the core's objects, and the layout of results.

Layer data travel as napari *layer-data tuples* ``(data, kwargs, layer_type)``, so this
package imports neither napari nor Qt (the model reader uses it too). Layers are read
duck-typed (``layer.data``, ``layer.scale``, ``layer.features``). One concept a module:

- :mod:`.names`: the layers' names, metadata keys and the beads' statuses;
- :mod:`.frame`: where an image lies in world coordinates, the result slots around it;
- :mod:`.points`: detected beads as a Points layer and back;
- :mod:`.figure`: titles and colour bars that make the slots read as one figure;
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
from .figure import colorbar_layers, map_layers, titles_layer
from .frame import (
    Frame,
    LayerTuple,
    bead_plane,
    below_others,
    beside,
    free_slot,
    image_plane,
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
    family_layers,
    gallery_cell,
    gallery_index,
    gallery_layers,
    heldout_layers,
    operator_layers,
    psf_layers,
)

__all__ = [*_names, "FIT_VERDICTS", "Frame", "GALLERY_GAP", "LayerTuple", "advice_layers",
           "bead_plane", "beads_from_points", "beads_layer", "below_others", "beside",
           "colorbar_layers",
           "ensure_bead_features", "find_layer", "fix_ids", "focus_on_step", "for_a_new_fit",
           "free_slot", "gallery_cell", "gallery_index", "gallery_layers", "group_layers",
           "heldout_layers", "hot_pixels_from_layer", "hot_pixels_layer", "image_plane",
           "input_images", "is_input_image", "map_layers", "operator_layers", "psf_layers",
           "remove_step", "set_statuses",
           "show_layers", "step_layers", "family_layers", "titles_layer", "user_beads"]
