"""Stage 3, diagnosis: judge a model on its beads' raw pixels and close the loop.

Takes an image and a model (or learns one with stage 2); gives honest residuals under a
camera noise model estimated from the image (:mod:`..beads.noise`, :mod:`.residuals`), every
bead judged by a model that never saw it (:mod:`.crossfit`), residual tests that point
at what the model lacks (:mod:`.analysis`, :mod:`.photometry`), and the loop that adds
an effect (:mod:`.effects`) only when held-out beads say it helps (:mod:`.loop`,
:func:`.loop.diagnose`). Imports ``model``, ``beads`` and ``common``.
"""
