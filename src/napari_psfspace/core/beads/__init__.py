"""Stage 1, beads: from a bead image to clean, centred patches.

Takes a 2-D image and a PSF radius; gives the bead table (:class:`.detect.Beads`:
positions, status of each candidate: kept, saturated, border, neighbour, faint, ...),
sub-pixel centres (:mod:`.centering`), hot pixels and cosmic rays (:mod:`.spikes`), the
camera's noise model read from the image (:mod:`.noise`: the diagnosis, the deblurring
and the 3D steps weigh their residuals with it), and
the windowed, background-free, sum-1 patches of the kept beads (:mod:`.patches`,
:mod:`.background`, :mod:`.window`), with what a bead's size does to its image
(:mod:`.sphere`). Imports only ``common``.
"""
