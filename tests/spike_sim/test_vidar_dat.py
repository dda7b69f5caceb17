"""Raw Vidar .dat I/O: orientation against spikezoo's REDS sample, round trips, camera files, malformed sizes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from polinfra.errors import DataFormatError
from spike_sim.vidar_dat import DatWriter, dat_frame_count, iter_dat, read_dat, write_dat

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real_spikes"
REDS = REAL / "spikezoo_reds_200_part1_key_id151.dat"
REDS_GT = REAL / "spikezoo_reds_200_part1_key_id151_gt.png"


@pytest.mark.skipif(not REDS.is_file(), reason=f"shared REDS sample not found at {REDS}")
def test_reds_sample_orientation_matches_ground_truth():
    """TFP of frames 130..170 (x 1/0.6) correlates with the GT PNG only when rows are flipped on read."""
    import imageio.v3 as iio

    assert dat_frame_count(REDS, 250, 400) == 301
    gt = iio.imread(REDS_GT).astype(np.float64)
    gt = gt.mean(-1) if gt.ndim == 3 else gt
    s = read_dat(REDS, 250, 400, frames=slice(130, 171))
    assert s.shape == (41, 250, 400)
    tfp = s.mean(0) / 0.6
    r_ok = np.corrcoef(tfp.ravel(), gt.ravel())[0, 1]
    r_bad = np.corrcoef(read_dat(REDS, 250, 400, frames=slice(130, 171), flip=False).mean(0).ravel(), gt.ravel())[0, 1]
    assert r_ok > 0.95
    assert r_bad < 0.3
    # lazy slice equals the full read
    assert np.array_equal(read_dat(REDS)[130:171], s)


def test_round_trip_is_bit_exact(tmp_path, np_rng):
    s = (np_rng.random((37, 250, 400)) < 0.2).astype(np.uint8)
    p = write_dat(tmp_path / "a.dat", s)
    assert p.stat().st_size == 37 * 12500
    assert np.array_equal(read_dat(p), s)
    assert np.array_equal(np.concatenate(list(iter_dat(p, chunk_frames=10))), s)


def test_layout_is_lsb_first_and_upside_down(tmp_path):
    """Pixel (row 0, col 0) of an upright frame is bit 0 of the first byte of the LAST stored row."""
    s = np.zeros((1, 8, 16), np.uint8)
    s[0, 0, 0] = 1
    s[0, 7, 9] = 1
    raw = np.frombuffer(write_dat(tmp_path / "b.dat", s).read_bytes(), np.uint8)
    assert raw.size == 16
    assert raw[7 * 2] == 1  # stored row 7 = upright row 0, bit 0
    assert raw[1] == 1 << 1  # stored row 0 = upright row 7, column 9 = byte 1 bit 1


def test_packed_writer_matches_plain_writer(tmp_path, np_rng):
    s = (np_rng.random((5, 16, 40)) < 0.5).astype(np.uint8)
    packed = np.packbits(s.reshape(5, -1), axis=1, bitorder="little")
    with DatWriter(tmp_path / "c.dat") as w:
        w.write_packed(packed[:2], 16, 40)
        w.write_packed(packed[2:], 16, 40)
    assert (tmp_path / "c.dat").read_bytes() == write_dat(tmp_path / "d.dat", s).read_bytes()


def test_camera_files_with_416_columns_drop_the_header(tmp_path, np_rng):
    s = (np_rng.random((3, 250, 416)) < 0.3).astype(np.uint8)
    p = write_dat(tmp_path / "cam.dat", s)
    got = read_dat(p, 250, 400)
    assert got.shape == (3, 250, 400)
    assert np.array_equal(got, s[:, :, :400])


def test_malformed_size_raises(tmp_path):
    p = tmp_path / "bad.dat"
    p.write_bytes(b"\0" * 12501)
    with pytest.raises(DataFormatError, match="not a whole number"):
        read_dat(p)
    with pytest.raises(DataFormatError, match="not found"):
        read_dat(tmp_path / "missing.dat")


def test_failed_write_leaves_no_file(tmp_path):
    with pytest.raises(RuntimeError):
        with DatWriter(tmp_path / "x.dat") as w:
            w.write(np.zeros((2, 8, 8), np.uint8))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_frame_slices_negative_and_reversed(tmp_path, np_rng):
    """frames= accepts any slice, like indexing the full stream (negative indices, steps, reversed)."""
    s = (np_rng.random((9, 8, 16)) < 0.4).astype(np.uint8)
    p = write_dat(tmp_path / "s.dat", s)
    for sl in (slice(None, None, -1), slice(-3, None), slice(7, 1, -2), slice(1, 8, 3), slice(5, 5), slice(-100, 100)):
        assert np.array_equal(read_dat(p, 8, 16, frames=sl), s[sl]), sl
    with pytest.raises(DataFormatError, match="slice"):
        read_dat(p, 8, 16, frames=[1, 2])


def test_camera_file_whose_size_also_fits_plain_frames(tmp_path, np_rng, caplog):
    """25 camera frames of 416 columns = 26 plain frames of 400 (325000 bytes): auto reads plain frames and
    warns; head_columns=16 reads the camera file; head_columns=0 refuses a size that fits only camera frames.
    """
    s = (np_rng.random((25, 250, 416)) < 0.3).astype(np.uint8)
    p = write_dat(tmp_path / "cam.dat", s)
    with caplog.at_level("WARNING"):
        assert read_dat(p).shape == (26, 250, 400)
    assert any("head_columns=16" in r.getMessage() for r in caplog.records)
    assert dat_frame_count(p, head_columns=16) == 25
    assert np.array_equal(read_dat(p, head_columns=16), s[:, :, :400])
    assert np.array_equal(np.concatenate(list(iter_dat(p, head_columns=16, chunk_frames=7))), s[:, :, :400])
    q = write_dat(tmp_path / "cam3.dat", s[:3])
    with pytest.raises(DataFormatError, match="not a whole number"):
        read_dat(q, head_columns=0)
    with pytest.raises(DataFormatError, match="head_columns"):
        read_dat(q, head_columns=8)


def test_odd_geometry_and_single_frame(tmp_path):
    """One frame is a valid file; H*W not divisible by 8 cannot be written (.dat frames are whole bytes)."""
    from polinfra.errors import ShapeError

    one = np.zeros((1, 250, 400), np.uint8)
    one[0, 10, 20] = 1
    assert np.array_equal(read_dat(write_dat(tmp_path / "one.dat", one)), one)
    with pytest.raises(ShapeError, match="divisible by 8"):
        write_dat(tmp_path / "odd.dat", np.zeros((2, 3, 3), np.uint8))
    assert not (tmp_path / "odd.dat").exists()
