"""Training windows from a dataset mixing layer groups and 3-D object groups (full tier): the stored-window
reader takes both kinds, and a 3-D group's items have the window shapes and its stored ground truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

H, W, CROP = 20, 32, 8


def _require_mitsuba():
    import importlib.util

    if importlib.util.find_spec("mitsuba") is None:
        pytest.skip("mitsuba is not installed")


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """One layer group (analytic) and one 3-D object group (full tier, 4 spp), both train, 32 x 20, 30 ms."""
    _require_mitsuba()
    from polspike.pipeline.dataset import build_dataset
    from polspike.pipeline.manifest import dump_manifest

    man = {
        "format": "polspike-manifest/1", "name": "mix", "description": "a layer group and a 3-D object group", "allow_shared_content": True,
        "defaults": {"duration_s": 0.03, "keyframe_fps": 100.0, "camera": {"width": W, "height": H}, "spike_sim": {"preset": "default"}},
        "groups": [
            {"name": "layers", "split": "train", "tier": "analytic", "scene": "scenes/brewster.toml", "seed": 3},
            {"name": "objects", "split": "train", "tier": "full", "scene": "scenes/shop_window.toml", "seed": 5, "render": {"spp": 4}},
        ],
    }
    root = tmp_path_factory.mktemp("mix")
    (root / "m.toml").write_text(dump_manifest(man))
    build_dataset(root / "m.toml", root / "ds")
    return root / "ds"


def test_train_windows_come_from_both_kinds_of_group(mixed):
    from reconstruct.net.onthefly import WindowConfig
    from reconstruct.net.windows import StoreWindows

    ds = StoreWindows(mixed, WindowConfig(crop=CROP), split="train", seed=1, centre_every=9)
    names = [g.name for g in ds.groups]
    assert sorted(names) == ["layers", "objects"]
    seen = {names[ds.locate(j)[0]] for j in range(len(ds))}
    assert seen == {"layers", "objects"}


def test_object_group_items_have_window_shapes_and_its_ground_truth(mixed):
    from reconstruct.net.onthefly import ITEM_KEYS, WindowConfig
    from reconstruct.net.windows import StoreWindows
    from spike_sim.store import open_group

    cfg = WindowConfig(crop=CROP)
    ds = StoreWindows(mixed / "groups" / "objects", cfg, split=None, seed=2, crop="centre")
    assert len(ds) > 0
    item = ds[len(ds) // 2]
    assert set(item) == set(ITEM_KEYS)
    n = cfg.n_obs
    assert tuple(item["I"].shape) == (n, CROP, CROP) and tuple(item["zeta"].shape) == (n, CROP, CROP)
    assert tuple(item["phi"].shape) == (n,)
    for k in ("T", "R", "R_perp", "R_par", "phi_perp", "T_perp", "T_par"):
        assert tuple(item[k].shape) == (CROP, CROP), k
    for k in ITEM_KEYS:
        assert np.all(np.isfinite(np.asarray(item[k]))), k
    # T is the group's stored ground truth (S0 of T alone), linearly interpolated in time at the centre step
    _, c = ds.locate(len(ds) // 2)
    y0, x0 = (H - CROP) // 2, (W - CROP) // 2
    with open_group(mixed / "groups" / "objects") as g:
        out_steps = g.array("output/step_index")
        gtT = np.stack([g.gt_frame("T", m) for m in range(out_steps.size)])
    T_hand = np.array([[np.interp(c, out_steps, gtT[:, y, x]) for x in range(x0, x0 + CROP)] for y in range(y0, y0 + CROP)])
    assert float(np.max(T_hand)) > 0.0
    np.testing.assert_allclose(item["T"].numpy(), T_hand, atol=2e-3)  # float16-rounded
    assert 0.0 <= float(item["phi"][n // 2]) < math.pi
