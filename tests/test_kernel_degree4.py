"""kernel.py's degree-4 rule for middle-distance triangle pairs evaluates Dunavant's 6 points alone
(``_rules(..., groups=2)``): the same number, to the bit, as the 6 + 3 point pair it used to take Q6 from."""

from __future__ import annotations

import numpy as np

from hfrad.formfactors.kernel import _rules


def test_six_point_rule_alone_is_q6_of_the_embedded_pair_to_the_bit():
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(200):
        T = rng.normal(size=(2, 3, 3))
        T[1] += [0.0, 0.0, 2.0]        # the target triangle above the source, at various tilts
        cr = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
        N = cr / np.linalg.norm(cr, axis=1, keepdims=True)
        p = T[0]
        args = (*p.ravel(), *N[0], np.ascontiguousarray(T), np.ascontiguousarray(N), 1, 1e-12)
        q6, q3 = _rules(*args)
        alone, none = _rules(*args, 2)
        assert alone == q6 and none == 0.0
        checked += q6 != 0.0
    assert checked > 50                 # most pairs see each other
