"""Names: of the layers the plugin makes, of their metadata keys, and of the beads' statuses.

One place for every string a layer is found again by (a re-run updates the layer made
as that name, whatever napari renamed it to), so that the widgets, the reader and the
writer agree.
"""

from __future__ import annotations

from ..core.beads.detect import (
    COMPANION,
    HELDOUT,
    OFF_FOCUS,
    REJECTED,
    STATUS_MEANING,
    STATUSES,
    STRUCTURE,
)

#: Every status a bead of the Points layer can have ("rejected": by the user in the
#: review; not used for the model).
ALL_STATUSES = STATUSES
#: Ring colour of each status in the Points layer.
STATUS_COLORS = {
    "kept": "#3cff3c",
    "saturated": "#ff9900",
    "border": "#ffe135",
    "neighbour": "#29c8ff",
    "faint": "#a0a0a0",
    "outlier": "#ff40ff",
    REJECTED: "#ff2020",
    HELDOUT: "#ffffff",
    COMPANION: "#8a2be2",
    STRUCTURE: "#8b5a2b",
    OFF_FOCUS: "#ff6f91",
}
#: Names of the layers the plugin creates. A map's name ends with its unit in brackets:
#: "relative" where each tile is scaled to its largest magnitude (the metadata's "about"
#: says how).
BEADS = "beads"
GALLERY = "bead patches (relative)"
CURRENT = "patch on display"
PSF_GRID = "PSF grid (relative)"
BASIS = "PSF basis (relative)"
#: One weight map a basis PSF: ``WEIGHT.format(i)``, i = 1..
WEIGHT = "PSF weight {} (relative)"
HELDOUT_LAYER = "held-out residual (energy fraction)"
#: Each bead's own FWHM, where the model is one PSF (the unit follows in brackets).
BEAD_FWHM = "bead FWHM"
PSF_AT = "PSF at position (fraction per px)"
SUB_GRID = "family PSF grid (relative)"
SUB_BASIS = "family PSF basis (relative)"
SUB_SPACE = "family spatial maps (relative)"
#: Key of the subspace layer metadata that holds the OperatorFamily.
SUBSPACE_KEY = "psfspace_subspace"
HOT_PIXELS = "hot pixels"
#: Where one more clicked bead would help an identification most, and the clicked beads
#: it left out.
MORE_BEADS = "one more bead here"
LEFT_OUT = "clicked beads left out"
#: Key of the layer metadata that holds the operator (read by the model writer).
OPERATOR_KEY = "psfspace_operator"
#: Metadata key marking a layer the plugin made, with the name it asked for: found again
#: on a re-run even when napari renamed it ("beads [1]" beside a user's image "beads").
MADE_AS = "psfspace_layer"


#: Metadata key of the step that made a layer: a step's layers are one group, replaced
#: together on a re-run and removed together (:func:`remove_step`).
STEP_KEY = "psfspace_step"

__all__ = ["ALL_STATUSES", "BASIS", "BEAD_FWHM", "BEADS", "CURRENT", "GALLERY", "HELDOUT_LAYER",
           "HOT_PIXELS", "LEFT_OUT", "MADE_AS", "MORE_BEADS", "OPERATOR_KEY", "PSF_AT",
           "PSF_GRID", "STATUS_COLORS", "STATUS_MEANING", "STEP_KEY", "SUBSPACE_KEY",
           "SUB_BASIS", "SUB_GRID", "SUB_SPACE", "WEIGHT"]
