"""Stage 4, subspace (issue 11): a family of operators from many bead images.

Will take the operators (or patches) of many images of one microscope under varying
conditions; will give a spatial basis ``a_j`` and one small matrix ``Gamma_k`` per image,
the family being the cone of the ``Gamma_k``. May import ``model``, ``beads`` and
``common``; empty until issue 11.
"""
