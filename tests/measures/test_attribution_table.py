"""The attribution methods' one table (harness.measures.attribution.METHODS): every row runs through `attribute`,
the passes `analyse` computes follow the rows, one default list for runs, and sanity's own list derived from it."""

from __future__ import annotations

import numpy as np
import pytest

from harness.measures import attribution as A
from tests.measures.test_attribution import COLS, ROWS, TARGET, toy_step


def test_every_method_of_the_table_gives_a_map_per_camera():
    analysis = A.analyse(toy_step(), gradients=A.needs_gradients(A.BASE_METHODS),
                         occlusion=A.needs_occlusion(A.BASE_METHODS))
    names = A.parse_methods(",".join(A.BASE_METHODS), 1)
    assert names == ("attention:0", "rollout", "grad-attention", "saliency", "occlusion", "random")
    for name in names:
        maps = A.attribute(analysis, name, seed=3)
        assert list(maps) == ["image_primary"] and maps["image_primary"].shape == (ROWS, COLS), name
    for name in ("grad-attention", "saliency", "occlusion"):  # the maps that know the toy policy reads one patch
        assert int(np.argmax(A.attribute(analysis, name)["image_primary"])) == TARGET, name
    with pytest.raises(ValueError, match="unknown attribution method 'lime'"):
        A.attribute(analysis, "lime")


def test_the_passes_follow_the_rows():
    assert A.needs_gradients(["attention:1", "saliency"]) and A.needs_gradients(["grad-attention"])
    assert not A.needs_gradients(["attention:1", "rollout", "occlusion", "random", ""])
    assert A.needs_occlusion(["occlusion"]) and not A.needs_occlusion(["saliency", "random", ""])
    with pytest.raises(ValueError, match="occlusion needs analyse"):
        A.attribute(A.analyse(toy_step(), gradients=False), "occlusion")


def test_one_default_list_and_sanitys_own_choice():
    from harness.gate import sanity

    assert A.DEFAULT_METHODS == "attention,rollout,grad-attention,saliency"  # what a run computes unless told
    assert sanity.DEFAULT_METHODS == "attention,rollout,grad-attention,saliency,occlusion"  # plus the reference
    assert A.parse_methods(A.DEFAULT_METHODS, 2)[-1] == "random"  # the control, always added
    order = sorted(A.BASE_METHODS, key=A.display_rank)
    assert order == ["attention", "rollout", "grad-attention", "saliency", "random", "occlusion"]
