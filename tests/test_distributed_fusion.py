"""Fused group tasks (hfrad.distributed.run._fused_groups, tasks.group_tree_task): a group whose blocks form a
node of the HF tree runs its leaves and merges as one Dask task, with the same result."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad import DaskBackend, LocalBackend, PrecomputeOptions
from hfrad.distributed import connect
from hfrad.distributed.run import _fused_groups, task_order
from hfrad.distributed.tiles import TilePlan
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene


def _plan(m, g, b=4):
    return TilePlan(n=m * b, block_size=b, group=g, band=1)


@pytest.mark.parametrize("m, g", [(13, 4), (16, 8), (7, 2), (9, 4)])
def test_fused_groups_are_the_whole_groups_subtrees(m, g):
    order = task_order(m)
    fused = _fused_groups(order, m, _plan(m, g), set(), panel_leaves=m)
    position = {node: i for i, (_, node, _) in enumerate(order)}
    assert sorted(J for J, _ in fused.values()) == list(range(m // g))     # every whole group, no partial one
    for node, (J, merges) in fused.items():
        assert len(merges) == g - 1 and merges[-1][0] == node
        below = {x for _, l, r in merges for x in (l, r)}
        assert {x for x in below if x < m} == set(range(J * g, (J + 1) * g))
        # in the tree's order, each merge after its children
        assert [position[x] for x, _, _ in merges] == sorted(position[x] for x, _, _ in merges)
        for x, l, r in merges:
            assert position[l] < position[x] and position[r] < position[x]


def test_resumed_or_panelled_groups_are_not_fused():
    m, g = 16, 4
    order = task_order(m)
    fused = _fused_groups(order, m, _plan(m, g), {5}, panel_leaves=m)
    assert sorted(J for J, _ in fused.values()) == [0, 2, 3]
    assert _fused_groups(order, m, _plan(m, g), set(), panel_leaves=3) == {}
    assert _fused_groups(order, m, _plan(m, 1), set(), panel_leaves=m) == {}


def test_fused_run_equals_local(monkeypatch):
    """Groups of 2 blocks (fused: 5 group tasks for 10 leaves and their 5 merges) on 2 in-process workers:
    the local factorization, and one record per leaf and merge as unfused."""
    from hfrad.distributed import tiles

    monkeypatch.setattr(tiles, "MIN_GROUP_COLUMNS", 128)
    scene = load_scene("cornell", patches=600)
    local = factorize(scene, eps=0.02, near_field=32, backend=LocalBackend(reciprocity=False),
                      options=PrecomputeOptions(block_size=64))
    records = []
    from distributed import get_task_stream

    with connect(workers=2, processes=False) as cluster, get_task_stream(cluster.client) as stream:
        dist = factorize(scene, eps=0.02, near_field=32, backend=DaskBackend(scheduler=cluster, records=records),
                         options=PrecomputeOptions(block_size=64))
    keys = [str(t["key"]) for t in stream.data]
    assert sum(k.startswith("hfrad-group-") for k in keys) == 5
    assert not any(k.startswith(("hfrad-leafpart-", "hfrad-leaf-")) for k in keys)
    assert sum(k.startswith("hfrad-merge-") for k in keys) < 5     # only the merges above the groups
    m = -(-scene.n_patches // 64)
    info = dist.lowrank.info
    assert info["tile_group"] == 2 and info["tasks"] == 2 * m - 1
    assert sum(r["kind"] == "leaf" for r in records) == m
    assert dist.rank == local.rank
    assert dist.relative_error == pytest.approx(local.relative_error, rel=1e-4)
    B, B0 = dist.solve(scene.emission), local.solve(scene.emission)
    assert np.abs(B - B0).max() <= 1e-4 * np.abs(B0).max()
