"""Direct light conserves flux and stays out of closed rooms (issue 47, item 1).

In a closed room the patches' solid angles at a luminaire tile the sphere, so
the flux they receive, ``sum_p H_p A_p``, must equal the luminaire's flux
``integral of I dw`` (computed from the photometry alone, independently of the
patches) wherever the luminaire is and however it is aimed, 1 mm from a
surface included; a luminaire outside the room, however close to a wall,
sends nothing in.
"""

from __future__ import annotations

import numpy as np
import pytest

import hfrad
from hfrad.lighting import Luminaire, Photometry, caster_for, direct_illuminance, patch_direct_illuminance


def _rotational(fn, step):
    v = np.arange(0, 180 + step / 2, step)
    return Photometry("C", [0.0], v, fn(v)[None, :], name="test")


#: a smooth downlight, and a hard-edged 10-degree spot (its edge the hardest case for sampling)
DOWNLIGHT = _rotational(lambda v: np.where(v <= 90, 1200 * np.cos(np.radians(v)) ** 3
                                           + 100 * np.cos(np.radians(v)), 0.0), 0.5)
SPOT = _rotational(lambda v: np.where(v <= 10, 1000.0, 0.0), 0.25)


@pytest.fixture(scope="module")
def room():
    scene = hfrad.load_scene("furnace", patches=200)                # closed 1 m cube, faces looking in
    return scene, caster_for(scene)


def _received(room, ph, position, aim) -> float:
    scene, caster = room
    H = patch_direct_illuminance(scene, [Luminaire(ph, position, aim=aim)], caster=caster)[:, 0]
    return float(scene.areas @ H)


@pytest.mark.parametrize("gap", [1e-3, 1e-2, 0.3, 0.5])
@pytest.mark.parametrize("ph, rtol", [(DOWNLIGHT, 1e-3), (SPOT, 2e-2)], ids=["downlight", "spot"])
def test_flux_into_a_closed_room_equals_the_flux_received(room, gap, ph, rtol):
    """Aimed at the ceiling from ``gap`` below it: all of the flux lands (main lost 76-100% at 1 cm)."""
    phi = ph.flux(0.1)
    assert _received(room, ph, [0.37, 1 - gap, 0.61], [0, 1, 0]) == pytest.approx(phi, rel=rtol)
    # observed: downlight within 6e-4, spot within 1.6% (the 10-degree edge: samples ~2e-3 sr apart)


@pytest.mark.parametrize("position, aim", [([0.5, 0.5, 0.5], [1, 1, 1]), ([0.01, 0.4, 0.45], [-1, 0.2, 0]),
                                           ([0.999, 0.002, 0.998], [1, -1, 1])],
                         ids=["centre-to-corner", "1cm-from-wall", "in-a-corner"])
def test_flux_balance_any_position_and_aim(room, position, aim):
    phi = DOWNLIGHT.flux(0.1)
    assert _received(room, DOWNLIGHT, position, aim) == pytest.approx(phi, rel=1e-3)


@pytest.mark.parametrize("gap", [1e-6, 1e-3, 0.3])
def test_a_luminaire_behind_each_wall_lights_nothing_inside(room, gap):
    """Just outside each of the six walls, aimed in: no flux on any patch, no lux at points inside."""
    scene, caster = room
    rng = np.random.default_rng(0)
    P = rng.uniform(0.05, 0.95, (50, 3))
    for axis in range(3):
        for side in (0, 1):
            pos = np.array([0.43, 0.57, 0.38])
            pos[axis] = -gap if side == 0 else 1 + gap
            aim = np.zeros(3)
            aim[axis] = 1.0 if side == 0 else -1.0
            lum = Luminaire(DOWNLIGHT, pos, aim=aim)
            assert _received(room, DOWNLIGHT, pos, aim) == 0.0, (axis, side)
            N = np.tile(-aim, (len(P), 1))                           # facing the luminaire
            assert not direct_illuminance([lum], P, N, caster=caster).any(), (axis, side)


def test_a_flush_luminaire_lights_the_room(room):
    """On the ceiling's plane, aimed down: the flux goes in (the mounting surface does not block it)."""
    phi = DOWNLIGHT.flux(0.1)
    assert _received(room, DOWNLIGHT, [0.37, 1.0, 0.61], [0, -1, 0]) == pytest.approx(phi, rel=1e-3)


def test_flux_balance_of_a_large_opening_near_the_ceiling(room):
    """A 0.6 m panel 5 cm under the ceiling is an area source (36 points) for most patches: flux kept."""
    v = np.arange(0, 180.25, 0.5)
    panel = Photometry("C", [0.0], v, np.where(v <= 90, 1000 * np.cos(np.radians(v)), 0.0)[None],
                       size=(0.6, 0.6, 0.0), name="panel")
    assert _received(room, panel, [0.5, 0.95, 0.5], [0, -1, 0]) == pytest.approx(panel.flux(0.1), rel=1e-3)
    # observed 2.4e-4
