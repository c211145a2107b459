"""The accumulator's check of a RegionFeatures message against itself."""

import numpy as np
import pytest

from olsplat_msgs import RegionFeatures
from olsplat_nodes.transport.convert import split_bank


def message(**change):
    labels = np.zeros((2, 4, 6), np.int32)
    labels[1, :, 3:] = 1
    fields = dict(
        name="v",
        label_maps=labels,
        level_sizes=np.array([1, 2], np.int32),
        features=np.ones((3, 8), np.float16),
        width=6,
        height=4,
    )
    fields.update(change)
    return RegionFeatures(**fields)


def test_split_bank_gives_each_level_its_rows():
    labels, bank = split_bank(message())
    assert labels.shape == (2, 4, 6)
    assert [b.shape for b in bank] == [(1, 8), (2, 8)]
    assert bank[0].dtype == np.float32


@pytest.mark.parametrize(
    "change, problem",
    [
        ({"width": 7}, "label maps are (2, 4, 6), the image is 4x7"),
        ({"level_sizes": np.array([1, 1], np.int32)}, "do not match 2 levels and 3 feature rows"),
        ({"features": np.full((3, 8), np.nan, np.float16)}, "NaN"),
        ({"level_sizes": np.array([2, 1], np.int32)}, "level 1: labels span 0..1, the level has 1 regions"),
    ],
)
def test_split_bank_names_the_inconsistency(change, problem):
    with pytest.raises(ValueError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        split_bank(message(**change))
