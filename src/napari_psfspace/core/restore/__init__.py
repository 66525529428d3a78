"""Stage 5, restore (issue 12): blind deblurring with a family of operators.

Will take an image of a sample with a few beads and a subspace of stage 4; will identify
an operator of the family from the beads and solve a sparse + smooth deconvolution
(identification, deblurring and their solvers). May import every stage before it;
empty until issue 12.
"""
