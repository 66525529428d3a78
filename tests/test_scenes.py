"""The scene set (core/simulation/scene_set.py, issue 9): seeded, within its ranges, and
covering them, so that thresholds calibrated on it are calibrated on a family."""

import numpy as np
import pytest

from napari_psfspace.core.simulation.scene_set import RANGES, random_scene

SEEDS = range(24)


@pytest.fixture(scope="module")
def drawn():
    return [random_scene(seed, shape=(256, 256)) for seed in SEEDS]


def test_a_seed_gives_the_same_scene_again(drawn):
    image, truth, params = random_scene(5, shape=(256, 256))
    image0, truth0, params0 = drawn[5]
    np.testing.assert_array_equal(image, image0)
    np.testing.assert_array_equal(truth.positions, truth0.positions)
    assert params == params0
    assert not np.array_equal(drawn[5][0], drawn[6][0])


@pytest.mark.parametrize("key", ["pixel_size", "na", "wavelength", "spread", "offset",
                                 "read_noise"])
def test_each_drawn_value_lies_in_its_range_and_spreads_over_it(drawn, key):
    lo, hi = RANGES[key]
    values = np.array([p[key] for _, _, p in drawn])
    assert values.min() >= lo and values.max() <= hi, (key, values.min(), values.max())
    # 24 uniform draws cover most of the range (each end within a quarter of it)
    assert values.min() <= lo + 0.25 * (hi - lo) and values.max() >= hi - 0.25 * (hi - lo)


def test_bit_depths_and_aberrations_are_all_drawn(drawn):
    bits = {p["bits"] for _, _, p in drawn}
    kinds = {p["aberrations"] for _, _, p in drawn}
    assert bits == set(RANGES["bits"])
    assert kinds == set(RANGES["aberrations"])
    for image, _, p in drawn:  # the camera's integer type holds the bit depth
        assert int(image.max()) <= 2 ** p["bits"] - 1


def test_a_fixed_parameter_is_kept_and_a_range_is_respected():
    _, _, p = random_scene(2, shape=(256, 256), na=1.2, background=(10.0, 20.0), bits=8)
    assert p["na"] == 1.2 and 10.0 <= p["background"] <= 20.0 and p["bits"] == 8
