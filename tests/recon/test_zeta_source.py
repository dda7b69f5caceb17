"""zeta sources: paper Eq. (2) in torch agrees with polphysics.zeta; physics maps from pane geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polinfra.errors import PolspikeError
from polphysics.zeta import zeta as zeta_np
from reconstruct.net.learned_zeta import zeta_learned
from reconstruct.physics.zeta import PaneMaps, pane_maps_from_geometry, zeta_from_maps


def test_eq2_matches_physics_module(np_rng):
    H, W = 4, 5
    maps = PaneMaps(np_rng.uniform(0.05, 0.3, (H, W)), np_rng.uniform(0, 0.05, (H, W)), np_rng.uniform(0, np.pi, (H, W)))
    phi = np.linspace(0, np.pi, 7)
    z = zeta_from_maps(maps, phi, dtype=torch.float64).numpy()
    ref = np.stack([zeta_np(p, maps.R_perp, maps.R_par, maps.phi_perp) for p in phi])
    assert np.allclose(z, ref, atol=1e-12)


def test_window_average_equals_fine_riemann_sum(np_rng):
    maps = PaneMaps(np.full((1, 1), 0.25), np.full((1, 1), 0.01), np.full((1, 1), 0.4))
    span = np.deg2rad(7.02)
    z = zeta_from_maps(maps, np.array([1.0]), span_rad=span, dtype=torch.float64).numpy()[0, 0, 0]
    u = 1.0 + span * ((np.arange(20000) + 0.5) / 20000 - 0.5)
    ref = zeta_np(u, 0.25, 0.01, 0.4).mean()
    assert abs(z - ref) < 1e-9


def test_zeta_equals_R_perp_along_phi_perp():
    maps = PaneMaps(np.full((2, 2), 0.2), np.full((2, 2), 0.03), np.full((2, 2), 0.7))
    z = zeta_from_maps(maps, np.array([0.7, 0.7 + np.pi / 2]), dtype=torch.float64)
    assert torch.allclose(z[0], torch.full((2, 2), 0.2, dtype=torch.float64))
    assert torch.allclose(z[1], torch.full((2, 2), 0.03, dtype=torch.float64))


def test_physics_maps_from_geometry_normal_incidence():
    from polphysics.geometry import PinholeCamera, Plane

    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=1.0, width=3, height=3)
    m = pane_maps_from_geometry(cam, Plane(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])), 1.5)
    assert np.allclose(m.R_perp, 0.04, atol=1e-4) and np.allclose(m.R_par, 0.04, atol=1e-4)  # ((n-1)/(n+1))^2


def test_learned_source_shapes_and_softmax_weights():
    import torch

    from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights

    m = init_weights(PolSpikeNet(NetConfig(feat_ch=8, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8), use_rir=False)), torch.Generator().manual_seed(0)).eval()
    I = 0.1 + 0.3 * torch.rand(2, 7, 10, 13, dtype=torch.float64, generator=torch.Generator().manual_seed(1))  # H, W not multiples of 4
    phi = torch.deg2rad(31.5 * torch.arange(7, dtype=torch.float64)).expand(2, 7)
    z, w = zeta_learned(m, I, phi)
    assert z.shape == I.shape and w.shape == I.shape and z.dtype == torch.float64
    assert bool(((z > 0) & (z < 1)).all())  # supp. Eq. (19): a sigmoid
    assert torch.allclose(w.sum(1), torch.ones(2, 10, 13, dtype=torch.float64), atol=1e-5)  # softmax over the window
    with pytest.raises(PolspikeError):
        zeta_learned(m, I[0], phi)
