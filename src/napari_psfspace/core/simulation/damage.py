"""The ways a camera image goes wrong, applied to a scene: for fuzzing every path of the
estimate, the noise model and the diagnosis (``tests/test_noise.py``,
``bench/bench_fuzz.py``).
"""

from __future__ import annotations

import numpy as np

#: Name of each damage, by its index in :func:`damaged`.
DAMAGES = ("none", "half clipped to the floor", "a third saturated", "flat background",
           "flat background with stray counts", "constant block in the centre")


def damaged(image: np.ndarray, kind: int, seed: int = 0) -> np.ndarray:
    """A copy of an integer image with damage ``kind`` (an index of :data:`DAMAGES`).

    The flat backgrounds keep the beads (pixels above the median by 3 sd) and set every
    other pixel to the median: every local level of the background is the same.
    """
    a = np.asarray(image).copy()
    if a.dtype.kind not in "ui":
        raise ValueError(f"`image` must hold integers (a camera's ADU), got {a.dtype}.")
    h, w = a.shape
    top = np.iinfo(a.dtype).max
    med = float(np.median(a))
    rng = np.random.default_rng(seed)
    if kind == 1:
        a[: h // 2] = a.min()
    elif kind == 2:
        a[:, : w // 3] = top
    elif kind == 3:
        a = np.where(a > med + 3 * a.std(), a, med).astype(image.dtype)
        a[0, 0] = max(0, int(med) - 1)
    elif kind == 4:
        a = np.where(a > med + 3 * a.std(), a, med + (rng.random(a.shape) < 0.01))
        a = a.astype(image.dtype)
        a[0, 0] = 0
    elif kind == 5:
        a[h // 4:3 * h // 4, w // 4:3 * w // 4] = int(med)
    elif kind != 0:
        raise ValueError(f"`kind` must be 0-{len(DAMAGES) - 1}, got {kind!r}.")
    return a


__all__ = ["DAMAGES", "damaged"]
