"""napari dock widgets over the headless core: pick beads, review patches, learn.

One module per dock widget; ``napari_psfspace._layers`` converts between layers and core
objects (the readers and writers use it too, without the widgets) and
``_worker`` runs core generators off the GUI thread. The manifest (``napari.yaml``)
names the classes directly, so importing this package stays cheap.
"""

__all__ = ["DeblurWidget", "DiagnoseWidget", "LearnOperatorWidget", "LearnFamilyWidget",
           "PickBeadsWidget", "ReviewPatchesWidget", "Volume3DWidget"]


def __getattr__(name: str):
    if name == "PickBeadsWidget":
        from ._pick_beads import PickBeadsWidget

        return PickBeadsWidget
    if name == "ReviewPatchesWidget":
        from ._review_patches import ReviewPatchesWidget

        return ReviewPatchesWidget
    if name == "LearnOperatorWidget":
        from ._learn_operator import LearnOperatorWidget

        return LearnOperatorWidget
    if name == "DiagnoseWidget":
        from ._diagnose import DiagnoseWidget

        return DiagnoseWidget
    if name == "LearnFamilyWidget":
        from ._learn_family import LearnFamilyWidget

        return LearnFamilyWidget
    if name == "DeblurWidget":
        from ._deblur import DeblurWidget

        return DeblurWidget
    if name == "Volume3DWidget":
        from ._volume import Volume3DWidget

        return Volume3DWidget
    raise AttributeError(name)
