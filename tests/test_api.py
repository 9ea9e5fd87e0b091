"""The public API as a user meets it: ``import hfrad`` and the names it exports."""

from __future__ import annotations

import numpy as np

import hfrad


def test_factorize_works_twice_after_the_subpackage_is_imported():
    # importing a module of the subpackage hfrad.factorize used to replace the
    # function hfrad.factorize by the subpackage (issue 10, item 4)
    import hfrad.factorize.hf  # noqa: F401
    from hfrad.factorize.hf import HFStream  # noqa: F401
    from hfrad.factorize.lowrank import LowRank  # noqa: F401

    scene = hfrad.load_scene("furnace", patches=60)
    first = hfrad.factorize(scene, eps=0.05)
    second = hfrad.factorize(scene, eps=0.05)
    assert callable(hfrad.factorize)
    from hfrad import factorize
    assert factorize is hfrad.factorize
    B1, B2 = first.solve(scene.emission), second.solve(scene.emission)
    np.testing.assert_array_equal(B1, B2)


def test_exports_resolve():
    for name in hfrad.__all__:
        assert getattr(hfrad, name) is not None, name
