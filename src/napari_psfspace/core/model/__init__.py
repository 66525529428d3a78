"""Stage 2, model: one space-varying operator from the beads of one image.

Takes the patches of stage 1; gives a :class:`.operator.ProductConvolution`
``H u = sum_i h_i * (alpha_i . u)``: a PCA basis with outlier rejection (:mod:`.pca`),
coefficient fields by weighted thin-plate splines (:mod:`.tps`, :mod:`.field`, or
Voronoi cells, :mod:`.voronoi`) kept inside the cone of observed PSFs (:mod:`.cone`),
the basis size chosen on held-out beads (:mod:`.heldout`, :mod:`.fewbeads` below 11
beads), a noise-aware refit (:mod:`.denoise`) and the motion-blur test
(:mod:`.motion`). :mod:`.estimate` runs the whole stage; :mod:`.review` gives the
numbers behind the patch review. The operator's file format is in
:mod:`.operator_file`. Imports ``beads`` and ``common``.
"""
