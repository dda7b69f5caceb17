"""HDF5 group store: packed spikes chunked in time, lazy reads, metadata, atomic publication."""

from __future__ import annotations

import numpy as np
import pytest

from polinfra.errors import DataFormatError, OutputError
from spike_sim.store import SPIKES_FILE, SUMMARY_FILE, GroupWriter, open_group


@pytest.mark.parametrize("compression", ["gzip", "none"])
def test_write_then_read_lazily(tmp_path, np_rng, compression):
    H, W, T = 10, 20, 130
    s = (np_rng.random((T, H, W)) < 0.3).astype(np.uint8)
    pk = np.packbits(s.reshape(T, -1), axis=1, bitorder="little")
    w = GroupWriter(tmp_path / "g", H, W, 20000.0, T, chunk_steps=32, compression=compression, attrs={"seed": 5, "config_json": {"a": 1}})
    for a in range(0, T, 17):
        w.write_spikes(pk[a : a + 17])
    w.write_array("polarizer/phi_true_rad", np.arange(T) * 0.01)
    w.close(summary={"note": "x"})
    g = open_group(tmp_path / "g")
    assert (g.n_steps, g.height, g.width, g.seed) == (T, H, W, 5)
    assert g.f["spikes"].chunks == (32, 25)
    assert np.array_equal(g.read(), s)
    assert np.array_equal(g.read(40, 77), s[40:77])
    assert np.array_equal(g.read_time(40 / 20000, 77 / 20000), s[40:77])
    assert np.array_equal(np.concatenate([c for _, c in g.iter_chunks(50)]), s)
    assert g.json_attr("config_json") == {"a": 1}
    assert g.summary["note"] == "x" and g.summary["complete"] is True
    np.testing.assert_array_equal(g.phi_true_rad, np.arange(T) * 0.01)
    g.close()


def test_incomplete_or_failed_group_is_not_published(tmp_path):
    w = GroupWriter(tmp_path / "g", 4, 8, 20000.0, 10)
    w.write_spikes(np.zeros((4, 4), np.uint8))
    with pytest.raises(OutputError, match="incomplete"):
        w.close()
    assert not (tmp_path / "g" / SPIKES_FILE).exists() and not (tmp_path / "g" / SUMMARY_FILE).exists()
    assert [p.name for p in (tmp_path / "g").iterdir()] == []
    with pytest.raises(DataFormatError):
        open_group(tmp_path / "g")


def test_refuses_to_overwrite_without_flag(tmp_path):
    w = GroupWriter(tmp_path / "g", 4, 8, 20000.0, 1)
    w.write_spikes(np.zeros((1, 4), np.uint8))
    w.close()
    with pytest.raises(OutputError, match="overwrite"):
        GroupWriter(tmp_path / "g", 4, 8, 20000.0, 1)
    GroupWriter(tmp_path / "g", 4, 8, 20000.0, 1, overwrite=True).close(ok=False)
